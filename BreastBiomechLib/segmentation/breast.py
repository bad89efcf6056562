"""The breast: body tissue anterior to the pectoral muscle, and its outer skin layer.

Arrays in SimpleITK's (z, y, x) order; lengths in millimetres. "Anterior" is LPS -y, found from
the image direction (:class:`VoxelGrid`), so axial and sagittal grids both work.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from BreastBiomechLib.segmentation.body import tissue_beneath
from BreastBiomechLib.segmentation.morphology import ball, largest_component, local_mean
from BreastBiomechLib.segmentation.volume import VoxelGrid


def breast_mask(body: np.ndarray, muscle: np.ndarray, grid: VoxelGrid) -> np.ndarray:
    """Body voxels anterior to the pectoral muscle's anterior surface (the pectoral fascia).

    Along every line of voxels in the anterior-posterior direction the fascia is the first muscle
    voxel; lines that miss the muscle (the field of view's edge, gaps in the segmentation) take
    the fascia of the nearest line that meets it. Raises ValueError when there is no muscle."""
    if not muscle.any():
        raise ValueError("the pectoral muscle is empty: the breast is delimited by it, so segment "
                         "the muscle (seed points on it) before the breast")
    m = grid.posterior_last(muscle)
    anterior = np.arange(m.shape[-1]) < muscle_front(m)[..., None]
    return body & grid.from_posterior_last(anterior) & ~muscle


def muscle_front(muscle_ap_last: np.ndarray) -> np.ndarray:
    """The index of the first muscle voxel on every anterior-posterior line of a muscle mask laid
    out by :meth:`~BreastBiomechLib.segmentation.volume.VoxelGrid.posterior_last`; lines that
    miss the muscle (the field of view's edge, gaps in the segmentation) take the front of the
    nearest line that meets it."""
    hit = muscle_ap_last.any(axis=-1)
    front = np.argmax(muscle_ap_last, axis=-1)
    if not hit.all():
        _, nearest = ndimage.distance_transform_edt(~hit, return_indices=True)
        front = front[tuple(nearest)]
    return front


def skin_layer(body: np.ndarray, breast: np.ndarray, grid: VoxelGrid, thickness_mm: float,
               muscle: np.ndarray | None = None) -> np.ndarray:
    """Breast voxels closer than ``thickness_mm`` to the nearest air voxel (the body surface; where
    the body is cut by the field of view's edge there is no surface). With the ``muscle`` mask,
    also the voxels where the muscle lies so close under the surface (the chest beside the
    breast) that there is no room for more than the skin and a voxel of partial volume: depth
    plus distance to the muscle under ``thickness_mm`` + 2 voxels (the tissue there is skin and
    its mixtures with muscle, which read as gland)."""
    if thickness_mm <= 0:
        return np.zeros_like(breast)
    depth = ndimage.distance_transform_edt(body, sampling=grid.spacing_zyx)
    skin = breast & (depth < thickness_mm)
    if muscle is not None and muscle.any():
        to_muscle = ndimage.distance_transform_edt(~muscle, sampling=grid.spacing_zyx)
        skin |= breast & (depth + to_muscle < thickness_mm + 2 * float(grid.spacing_zyx.max()))
    return skin


SKIN_SHELL_MM = 0.5       # depth resolution of the skin profile
SKIN_REFERENCE_MM = (6.0, 12.0)  # depths (below the skin) whose bright tissue is the reference
MAX_SKIN_MM = 6.0         # the deepest skin layer the profile may ask for (skin is at most ~3 mm)


def skin_depth(array: np.ndarray, body: np.ndarray, breast: np.ndarray, grid: VoxelGrid) -> float:
    """How deep (mm below the body surface) the skin and its partial-volume voxels reach, read
    from the image: in shells of the breast 0.5 mm thick, the 90th percentile of the intensity
    (the fat there, where fat is the brightest tissue) against that of the shells 6-12 mm deep;
    the skin reaches to the deepest shell that is darker than 0.9 of the reference. At most
    ``MAX_SKIN_MM``; 0 when the breast is too small to profile."""
    depth = ndimage.distance_transform_edt(body, sampling=grid.spacing_zyx)[breast]
    values = array[breast]
    shells = np.floor(depth / SKIN_SHELL_MM).astype(int)
    reference_shells = (shells * SKIN_SHELL_MM >= SKIN_REFERENCE_MM[0]) & (shells * SKIN_SHELL_MM < SKIN_REFERENCE_MM[1])
    if np.count_nonzero(reference_shells) < 100:
        return 0.0
    reference = float(np.percentile(values[reference_shells], 90))
    deepest = 0.0
    for shell in range(int(MAX_SKIN_MM / SKIN_SHELL_MM)):
        inside = shells == shell
        if np.count_nonzero(inside) >= 20 and np.percentile(values[inside], 90) < 0.9 * reference:
            deepest = (shell + 1) * SKIN_SHELL_MM
    return min(deepest, MAX_SKIN_MM)


SKIN_SIGNAL = 0.55  # T1-weighted skin signal over fat signal
SKIN_CONTRAST = 0.9  # a first layer whose bright voxels are darker than this share of fat's holds skin
FAT_TREND_MM = 20.0  # the scale over which the fat level may change (a bias field's)


def breast_surface(array: np.ndarray, body: np.ndarray, breast: np.ndarray, grid: VoxelGrid) -> np.ndarray:
    """``body`` with the surface of its breast part placed where a voxel is half tissue, for any
    outermost tissue. Whether a skin is imaged is read from the breast's first voxel layer: its
    bright voxels (90th percentile) are under :data:`SKIN_CONTRAST` of those 6-12 mm deep (the
    fat) with any skin of 0.8 mm or more, and as bright without one. With a skin, a voxel along
    the breast's surface belongs to the body when its intensity reaches half of skin's signal
    (:data:`SKIN_SIGNAL` of the local fat level: the brightest quarter of the breast 6-12 mm deep,
    averaged over ``FAT_TREND_MM``); without, half of the tissue 2-5 mm beneath. (The body's first
    rule, 0.3 of the tissue 2-5 mm beneath, is half of skin's signal only where that tissue is
    fat: not under a 3 mm skin, and not where no skin is imaged.) Voxels within 2 mm of the
    breast's surface are decided again; the rest of the body is kept as it is."""
    depth = ndimage.distance_transform_edt(body, sampling=grid.spacing_zyx)
    deep = breast & (depth >= SKIN_REFERENCE_MM[0]) & (depth < SKIN_REFERENCE_MM[1])
    first_mm = float(grid.spacing_zyx.min())
    first = breast & (depth >= first_mm) & (depth < first_mm + SKIN_SHELL_MM)
    if np.count_nonzero(deep) < 100 or np.count_nonzero(first) < 20:
        return body
    values = array.astype(np.float32)
    reference = np.percentile(values[deep], 90)
    if np.percentile(values[first], 90) < SKIN_CONTRAST * reference:
        bright = deep & (values >= np.percentile(values[deep], 75))
        level = SKIN_SIGNAL * local_mean(values, bright, FAT_TREND_MM / grid.spacing_zyx)
    else:
        inner = ndimage.binary_erosion(body, ball(grid.spacing_zyx, 2.0), border_value=1)
        level = tissue_beneath(values, inner, grid, within=breast)
    near = ndimage.binary_dilation(breast & (depth < 4.0), ball(grid.spacing_zyx, 3.0))
    band = near & ndimage.binary_dilation(body, ball(grid.spacing_zyx, 2.0)) & (depth < 2.0)
    band &= level > 0  # (no level where no tissue is near: left as it was)
    refined = (body & ~band) | (band & (values >= 0.5 * level))
    return ndimage.binary_fill_holes(largest_component(refined))
