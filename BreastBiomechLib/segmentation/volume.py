"""The MR volume as the segmentation sees it: checks, voxel geometry and seed points.

Arrays are SimpleITK's (z, y, x) index order; points are LPS millimetres (ITK physical space).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk


@dataclass(frozen=True)
class VoxelGrid:
    """The geometry of one image: ``spacing`` (x, y, z) in mm, and which array axis runs
    posterior (LPS +y) and in which sense, so that "anterior" has a meaning in index space."""

    image: sitk.Image
    spacing: tuple[float, float, float]
    ap_axis: int        # array axis (0 = z, 1 = y, 2 = x) most aligned with LPS y
    ap_sign: int        # +1: increasing index goes posterior, -1: anterior

    @property
    def spacing_zyx(self) -> np.ndarray:
        return np.asarray(self.spacing[::-1], dtype=float)

    def index_of(self, points_lps: np.ndarray) -> np.ndarray:
        """Nearest voxel (z, y, x) of each point (N, 3) LPS mm; -1 rows where outside the grid."""
        points = np.atleast_2d(np.asarray(points_lps, dtype=float))
        out = np.full((len(points), 3), -1, dtype=int)
        size = np.array(self.image.GetSize())
        for i, p in enumerate(points):
            ijk = np.rint(self.image.TransformPhysicalPointToContinuousIndex(tuple(p))).astype(int)
            if np.all(ijk >= 0) and np.all(ijk < size):
                out[i] = ijk[::-1]
        return out

    def posterior_last(self, array: np.ndarray) -> np.ndarray:
        """A view of ``array`` (z, y, x) with the anterior-posterior axis last, its index growing
        posteriorly (undone by :meth:`from_posterior_last`)."""
        moved = np.moveaxis(array, self.ap_axis, -1)
        return moved[..., ::-1] if self.ap_sign < 0 else moved

    def from_posterior_last(self, array: np.ndarray) -> np.ndarray:
        """An array laid out as :meth:`posterior_last` gives it, back in (z, y, x) order."""
        return np.moveaxis(array[..., ::-1] if self.ap_sign < 0 else array, -1, self.ap_axis)

    def to_image(self, array: np.ndarray) -> sitk.Image:
        """``array`` (z, y, x) as an image on this grid."""
        image = sitk.GetImageFromArray(array)
        image.CopyInformation(self.image)
        return image


def check_volume(image) -> VoxelGrid:
    """Check that ``image`` is a 3D scalar MR volume with contrast; a clear error names what is
    wrong. Returns its :class:`VoxelGrid`."""
    if not isinstance(image, sitk.Image):
        raise TypeError(f"segmentation needs a SimpleITK image, got {type(image).__name__}; "
                        "read files with BreastBiomechLib.io.images.read_image")
    if image.GetDimension() != 3:
        raise ValueError(f"segmentation needs a 3D volume; this image has {image.GetDimension()} "
                         "dimensions (stack 2D slices into one volume first)")
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise ValueError(f"segmentation needs a scalar volume; this one has "
                         f"{image.GetNumberOfComponentsPerPixel()} components per voxel (RGB or "
                         "vector images: extract the MR magnitude first)")
    if min(image.GetSize()) < 3:
        raise ValueError(f"the volume is too thin to segment: size {image.GetSize()} voxels "
                         "(need at least 3 along every axis)")
    array = sitk.GetArrayViewFromImage(image)
    if not np.all(np.isfinite(array)):
        raise ValueError("the volume holds NaN or infinite voxels; replace them before segmenting")
    lo, hi = float(array.min()), float(array.max())
    if hi - lo <= 1e-6 * max(abs(hi), 1.0):
        raise ValueError(f"the volume is constant ({lo:g} everywhere): there is no contrast to segment")
    direction = np.asarray(image.GetDirection(), dtype=float).reshape(3, 3)  # columns: i, j, k axes
    along_y = direction[1]  # LPS y component of the i, j, k axes
    itk_axis = int(np.argmax(np.abs(along_y)))
    if abs(along_y[itk_axis]) < 0.7:
        raise ValueError("the volume is oblique by more than 45 degrees to the anterior-posterior "
                         "axis; resample it to an axial or sagittal grid first")
    return VoxelGrid(image, tuple(float(s) for s in image.GetSpacing()), 2 - itk_axis,
                     int(np.sign(along_y[itk_axis])))


def seed_voxels(grid: VoxelGrid, seeds_lps, within: np.ndarray, what: str, where: str) -> np.ndarray:
    """Voxel indices (N, 3) (z, y, x) of the seed points (N, 3) LPS mm that lie inside ``within``.

    Seeds outside the image or outside ``within`` are dropped; if none is left a clear error
    names ``what`` the seeds were for and ``where`` they must be placed."""
    seeds = np.atleast_2d(np.asarray(seeds_lps, dtype=float)) if len(seeds_lps) else np.zeros((0, 3))
    if seeds.shape[1] != 3:
        raise ValueError(f"{what} seeds must be points with 3 coordinates (LPS mm), got shape {seeds.shape}")
    if len(seeds) == 0:
        raise ValueError(f"no {what} seeds given: place at least one point {where}")
    index = grid.index_of(seeds)
    inside = np.all(index >= 0, axis=1)
    inside[inside] = within[tuple(index[inside].T)]
    if not inside.any():
        raise ValueError(f"none of the {len(seeds)} {what} seeds lies {where}; check that the "
                         "points belong to this volume (LPS vs RAS) and sit on the structure")
    return index[inside]
