"""The breast: body tissue anterior to the pectoral muscle, and its outer skin layer.

Arrays in SimpleITK's (z, y, x) order; lengths in millimetres. "Anterior" is LPS -y, found from
the image direction (:class:`VoxelGrid`), so axial and sagittal grids both work.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from BreastBiomechLib.segmentation.volume import VoxelGrid


def breast_mask(body: np.ndarray, muscle: np.ndarray, grid: VoxelGrid) -> np.ndarray:
    """Body voxels anterior to the pectoral muscle's anterior surface (the pectoral fascia).

    Along every line of voxels in the anterior-posterior direction the fascia is the first muscle
    voxel; lines that miss the muscle (the field of view's edge, gaps in the segmentation) take
    the fascia of the nearest line that meets it. Raises ValueError when there is no muscle."""
    if not muscle.any():
        raise ValueError("the pectoral muscle is empty: the breast is delimited by it, so segment "
                         "the muscle (seed points on it) before the breast")
    # work with the anterior-posterior axis last, increasing posteriorly
    def to_ap(a):
        a = np.moveaxis(a, grid.ap_axis, -1)
        return a[..., ::-1] if grid.ap_sign < 0 else a

    m = to_ap(muscle)
    n = m.shape[-1]
    hit = m.any(axis=-1)
    front = np.argmax(m, axis=-1)
    if not hit.all():
        _, nearest = ndimage.distance_transform_edt(~hit, return_indices=True)
        front = front[tuple(nearest)]
    anterior = np.arange(n)[None, None, :] < front[..., None]
    anterior = anterior[..., ::-1] if grid.ap_sign < 0 else anterior
    return body & np.moveaxis(anterior, -1, grid.ap_axis) & ~muscle


def skin_layer(body: np.ndarray, breast: np.ndarray, grid: VoxelGrid, thickness_mm: float) -> np.ndarray:
    """Breast voxels closer than ``thickness_mm`` to the nearest air voxel (the body surface; where
    the body is cut by the field of view's edge there is no surface)."""
    if thickness_mm <= 0:
        return np.zeros_like(breast)
    depth = ndimage.distance_transform_edt(body, sampling=grid.spacing_zyx)
    return breast & (depth < thickness_mm)
