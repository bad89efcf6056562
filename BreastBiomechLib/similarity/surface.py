"""Distance from FE-predicted skin points to the body surface of the measured compressed image:
a geometric objective beside NMI, and a check of where a prediction leaves the measured shape.

Frames and units: points in LPS millimetres; distances in mm. The measured body is found as
the segmentation finds it (:func:`BreastBiomechLib.segmentation.body.body_mask`) unless given.
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from scipy import ndimage


class SurfaceDistance:
    """Unsigned distance (mm) to the surface of the body in ``measured`` (an MR volume), or of
    ``body`` (a mask on the same grid, non-zero inside) when given.

    The surface is the half level of the body mask smoothed by a Gaussian of ``smoothing_mm``
    (the voxels' stair steps, up to a slice thickness, would otherwise count as distance): points
    on it where the level crosses the edges between voxel centres (as marching cubes places its
    vertices), each with its outward normal. A point's distance is the distance along the normal
    of the nearest surface point, exact for a plane and second order in the point spacing near a
    smooth surface."""

    def __init__(self, measured: sitk.Image, body: sitk.Image | None = None, smoothing_mm: float = 1.5):
        from scipy.spatial import cKDTree

        from BreastBiomechLib.segmentation.body import body_mask
        from BreastBiomechLib.segmentation.volume import check_volume

        grid = check_volume(measured)
        if body is None:
            inside = body_mask(sitk.GetArrayFromImage(measured), grid)
        else:
            if body.GetSize() != measured.GetSize() or not np.allclose(body.GetSpacing(), measured.GetSpacing()):
                raise ValueError("the body mask must lie on the measured image's grid (same size and spacing)")
            inside = sitk.GetArrayFromImage(body) != 0
        if not inside.any() or inside.all():
            raise ValueError("the measured body fills none or all of the image: there is no surface to measure to")
        spacing_zyx = np.asarray(measured.GetSpacing(), float)[::-1]
        level = ndimage.gaussian_filter(inside.astype(np.float32), smoothing_mm / spacing_zyx, mode="nearest") - 0.5
        crossings = []
        for axis in range(3):
            low = [slice(None)] * 3
            high = [slice(None)] * 3
            low[axis], high[axis] = slice(0, -1), slice(1, None)
            a, b = level[tuple(low)], level[tuple(high)]
            where = np.nonzero((a > 0) != (b > 0))
            t = a[where] / (a[where] - b[where])
            zyx = np.stack(where, axis=1).astype(float)
            zyx[:, axis] += t
            crossings.append(zyx)
        zyx = np.concatenate(crossings)
        # outward normals: minus the level's gradient (central differences, per mm), in LPS
        gradient = np.stack([(ndimage.map_coordinates(level, (zyx + 0.5 * e).T, order=1, mode="nearest")
                              - ndimage.map_coordinates(level, (zyx - 0.5 * e).T, order=1, mode="nearest"))
                             / h for e, h in zip(np.eye(3), spacing_zyx)], axis=1)[:, ::-1]  # (x, y, z) index axes
        direction = np.asarray(measured.GetDirection(), float).reshape(3, 3)
        normal = -gradient @ direction.T
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
        origin = np.asarray(measured.GetOrigin(), float)
        self._points = origin + (zyx[:, ::-1] * np.asarray(measured.GetSpacing(), float)) @ direction.T
        self._normals = normal
        self._tree = cKDTree(self._points)
        self._to_index = np.linalg.inv(direction * np.asarray(measured.GetSpacing(), float))
        self._origin = origin
        self._size = np.asarray(measured.GetSize())

    def distances(self, points_mm: np.ndarray) -> np.ndarray:
        """Distance (mm) of each point (N, 3) LPS to the body surface; NaN for points outside
        the image (where the surface is not seen)."""
        return np.abs(self.signed_distances(points_mm))

    def signed_distances(self, points_mm: np.ndarray) -> np.ndarray:
        """Signed distance (mm) of each point (N, 3) LPS to the body surface along its outward
        normal: > 0 outside the body, < 0 inside; NaN for points outside the image."""
        points = np.atleast_2d(np.asarray(points_mm, float))
        ijk = (points - self._origin) @ self._to_index.T
        inside = np.all((ijk >= -0.5) & (ijk <= self._size - 0.5), axis=1)
        out = np.full(len(points), np.nan)
        if inside.any():
            _, nearest = self._tree.query(points[inside])
            out[inside] = np.einsum("ij,ij->i", points[inside] - self._points[nearest], self._normals[nearest])
        return out
