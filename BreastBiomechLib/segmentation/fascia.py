"""Tissue lying on the pectoral fascia with no fat plane between it and the muscle.

Glandular tissue pressed onto the muscle differs from it by little more than the noise (gland
420, muscle 330 against a noise of 55-67 at SNR 15-18), so the muscle's region growing, whose
window is three noise deviations wide, takes a glandular slab on the fascia into the muscle.
One voxel cannot tell them apart, but the slab is a layer: averaged along the muscle's surface,
at the same depth beneath it, the slab's voxels stand clear of the muscle's level while the
muscle's own voxels do not. This module finds those layers and gives them back to the breast;
gives back, too, what juts out of the muscle's front, which is smooth over centimetres where
the fascia is (patches of a slab too thin for the layers to show); and keeps the muscle one
layer along every anterior-posterior line: the border refinement, reaching over a slab from
neighbouring lines, can take the slab's front face (textured gland mixed with fat reads as
muscle mixed with fat) and leave the slab in a pocket behind it.

Arrays in SimpleITK's (z, y, x) order; lengths in millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from BreastBiomechLib.segmentation.breast import muscle_front
from BreastBiomechLib.segmentation.morphology import ball, local_mean, smooth_trend
from BreastBiomechLib.segmentation.volume import VoxelGrid

_NEIGHBOURS = np.ones((3, 3, 3), bool)


@dataclass
class FasciaSettings:
    """``depth_mm``: how deep beneath the fascia tissue may be found (a slab on the muscle);
    ``core_mm``: muscle deeper than this, away from its other faces, gives the muscle's own level
    and, averaged the same way layer by layer, what the muscle alone does (its texture, the bias
    field's drift, the noise): the threshold is the ``null_quantile`` of those averages;
    ``along_mm``: Gaussian sigma of the average along the surface, within one layer;
    ``significance``: and at least this many standard errors of that average; ``min_layers``:
    tissue must reach at least this many voxel layers beneath the surface (the first holds the
    muscle's partial volume with whatever lies in front); ``min_volume_mm3``: smaller patches
    are left to the muscle."""

    depth_mm: float = 8.0
    core_mm: float = 6.0
    along_mm: float = 2.5
    null_quantile: float = 0.999
    significance: float = 4.0
    min_layers: int = 3
    min_volume_mm3: float = 60.0


def tissue_on_fascia(array: np.ndarray, muscle: np.ndarray, breast: np.ndarray, front_level: np.ndarray,
                     grid: VoxelGrid, settings: FasciaSettings | None = None) -> np.ndarray:
    """The voxels of the ``muscle`` mask (bool) that hold the tissue in front of it rather than
    muscle: layers just beneath its surface towards the ``breast`` whose intensity, averaged
    along the surface at one depth, departs from the muscle's own level towards ``front_level``
    (the bias-corrected level of the tissue that may lie on the fascia, e.g. the glandular level
    of a fat/glandular fit; an array on the grid) by more than the muscle's own layers deeper
    down ever do (the ``null_quantile`` of theirs, and ``significance`` standard errors), and
    that reach the surface through such layers. The surface layer itself, which holds the
    muscle's partial volume with whatever lies in front, goes with the layer beneath it. Only
    where muscle lies deeper than ``core_mm`` within about 15 mm (its level to compare with)."""
    settings = settings or FasciaSettings()
    found = np.zeros_like(muscle)
    if not breast.any() or not muscle.any():
        return found
    # worked in the muscle's bounding box with room for the trend and the depths looked at
    margin = np.ceil(20.0 / grid.spacing_zyx).astype(int)
    hits = np.nonzero(muscle)
    box = tuple(slice(max(int(h.min()) - m, 0), int(h.max()) + m + 1) for h, m in zip(hits, margin))
    found[box] = _on_fascia(array[box], muscle[box], breast[box],
                            np.broadcast_to(np.asarray(front_level, dtype=np.float32), array.shape)[box],
                            grid.spacing_zyx, settings)
    return found


def _on_fascia(array: np.ndarray, muscle: np.ndarray, breast: np.ndarray, front_level: np.ndarray,
               spacing: np.ndarray, settings: FasciaSettings) -> np.ndarray:
    """:func:`tissue_on_fascia` on one box of the volume."""
    empty = np.zeros_like(muscle)
    if not breast.any():
        return empty
    depth = ndimage.distance_transform_edt(~breast, sampling=spacing)
    # away from the muscle's other faces (the fat plane or air behind it, its edges), whose
    # partial volume would brighten the averages
    interior = muscle & ndimage.binary_erosion(muscle | breast, ball(spacing, 2.0))
    core = interior & (depth > settings.core_mm)
    if core.sum() < 50:
        return empty
    # the muscle's own level, only where deep muscle lies near (elsewhere a wider trend would
    # miss the bias field's drift by more than the tissue on the fascia stands out)
    level = smooth_trend(array, core, 15.0, spacing)
    interior &= level > 0
    residual = (array - level)[core]
    noise = 1.4826 * float(np.median(np.abs(residual - np.median(residual))))
    # layers counted in voxel faces from the breast, not in millimetres: across thick slices
    # the voxel next to the breast is 3 mm deep yet holds the surface's partial volume
    layer_of = np.where(muscle, ndimage.distance_transform_cdt(~breast, metric="taxicab"), 0)
    towards = np.sign(front_level - level)
    sigma = settings.along_mm / spacing

    def excess(layer):
        return towards * (local_mean(array, layer, sigma) - level), noise * _mean_error_factor(layer, sigma)

    null = [excess(core & (layer_of == k))[0][core & (layer_of == k)] for k in np.unique(layer_of[core])[:6]]
    if sum(len(n) for n in null) < 50:
        return empty
    threshold = float(np.quantile(np.concatenate(null), settings.null_quantile))
    kept = muscle & (layer_of == 1)
    removed = np.zeros_like(muscle)
    for k in range(2, int(layer_of.max()) + 1):
        layer = interior & (layer_of == k) & (depth <= settings.depth_mm)
        if not layer.any():
            break
        above, error = excess(layer)
        kept = layer & (above > np.maximum(threshold, settings.significance * error)) \
            & ndimage.binary_dilation(kept, _NEIGHBOURS)
        if not kept.any():
            break
        removed |= kept
    if not removed.any():
        return empty
    removed |= muscle & (layer_of == 1) & ndimage.binary_dilation(removed & (layer_of == 2), _NEIGHBOURS)
    labels, count = ndimage.label(removed, _NEIGHBOURS)
    index = np.arange(count + 1)
    volume = ndimage.sum_labels(np.ones_like(labels), labels, index) * float(np.prod(spacing))
    reach = ndimage.maximum(np.where(removed, layer_of, 0), labels, index)
    keep = index[(volume >= settings.min_volume_mm3) & (reach >= settings.min_layers)]
    return np.isin(labels, keep[keep > 0])


def _mean_error_factor(weights: np.ndarray, sigma_vox) -> np.ndarray:
    """sqrt(sum w_i^2) / sum w_i of the Gaussian-weighted mean over ``weights`` (the standard
    error of :func:`local_mean` per unit noise), from the discrete kernels themselves."""
    w = weights.astype(np.float32)
    total, squares = w, w
    for axis, s in enumerate(np.broadcast_to(np.asarray(sigma_vox, dtype=float), (3,))):
        radius = max(int(np.ceil(4 * s)), 1)
        kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / max(s, 1e-6)) ** 2)
        kernel /= kernel.sum()
        total = ndimage.correlate1d(total, kernel, axis=axis, mode="nearest")
        squares = ndimage.correlate1d(squares, kernel**2, axis=axis, mode="nearest")
    return np.where(total > 1e-3, np.sqrt(squares) / np.maximum(total, 1e-3), np.inf).astype(np.float32)


def one_layer(muscle: np.ndarray, body: np.ndarray, grid: VoxelGrid, film_mm: float = 3.0) -> np.ndarray:
    """The pectoral muscle ``muscle`` (bool) made one layer along every anterior-posterior line
    of voxels, as the breast in front of it is delimited (:func:`~BreastBiomechLib.segmentation.
    breast.breast_mask`): a thin first run lying in front of breast tissue that lies in front of
    more muscle (:func:`film_in_front`) is given back to the breast, then the ``body`` voxels
    left between the muscle's front and its back on a line (cavities open to the side, which
    hole filling cannot close) are filled: the breast, delimited by the muscle's front, would
    leave them with no tissue at all."""
    mask = muscle & ~film_in_front(muscle, body, grid, film_mm)
    axis = grid.ap_axis
    ahead = np.cumsum(mask, axis=axis) > 0
    behind = np.flip(np.cumsum(np.flip(mask, axis), axis=axis), axis) > 0
    return mask | (body & ahead & behind)


def film_in_front(muscle: np.ndarray, body: np.ndarray, grid: VoxelGrid, thickness_mm: float) -> np.ndarray:
    """The voxels of ``muscle`` (bool) that lie, along their anterior-posterior line of voxels, in
    front of breast tissue that lies in front of more muscle: a first run of muscle voxels no
    thicker than ``thickness_mm``, then body voxels that are not muscle, then a thicker run.

    The pectoral muscle lies behind all of the breast, so such a film cannot be muscle: it is the
    front face of tissue on the fascia (a textured glandular slab mixed with fat reads as muscle
    mixed with fat) that the border refinement took in over the slab by way of the neighbouring
    lines, and left the slab itself in a pocket that belongs to neither."""
    m, inside = grid.posterior_last(muscle), grid.posterior_last(body)
    n = m.shape[-1]
    position = np.arange(n)
    hit = m.any(axis=-1, keepdims=True)
    start = np.argmax(m, axis=-1)[..., None]
    after = position > start
    end = np.where(hit & (~m & after).any(axis=-1, keepdims=True),
                   np.argmax(~m & after, axis=-1)[..., None], n)
    behind = m & (position >= end)
    second = np.where(behind.any(axis=-1, keepdims=True), np.argmax(behind, axis=-1)[..., None], n)
    gap = (position >= end) & (position < second)
    past = ~m & (position > second)
    second_end = np.where(past.any(axis=-1, keepdims=True), np.argmax(past, axis=-1)[..., None], n)
    thickness = (end - start) * float(grid.spacing_zyx[grid.ap_axis])
    film = (hit & (second < n) & (inside | ~gap).all(axis=-1, keepdims=True)
            & (thickness <= thickness_mm) & (second_end - second > end - start))
    return grid.from_posterior_last(film & (position >= start) & (position < end))


def ahead_of_fascia(muscle: np.ndarray, probability: np.ndarray, glandular: np.ndarray, grid: VoxelGrid,
                    window_mm: float = 30.0, share: float = 0.15, local_mm: float = 5.0) -> np.ndarray:
    """The voxels of ``muscle`` (bool) lying in front of the fascia as the muscle's own front
    shows it: on every anterior-posterior line of voxels the front's position to a fraction of a
    voxel from the muscle's partial-volume ``probability`` (float, the structure's volume
    fraction per voxel: the first muscle voxel holds muscle behind the fascia for its fraction,
    the voxel in front for its fraction below one half), and the running median of that
    position over ``window_mm`` across the coronal plane. Muscle voxels that this smooth fascia
    leaves wholly in front of it by a voxel or more go back to the breast. So do those that the
    fascia leaves at most ``share`` muscle where the voxel in front of them reads as gland
    (``glandular``, bool); there the fascia is the Gaussian-weighted mean (sigma ``local_mm``)
    of the positions of the lines around with fat in front that lie within a voxel of the
    median (the median of a curved chest's front over the window lies behind its middle: by
    half a voxel at 1.5 mm on a 100 mm radius).

    The fascia is smooth over centimetres (a chest's curvature moves it by about a millimetre
    across 30 mm), the muscle's front only as rough as its partial-volume voxel; tissue lying on
    the fascia that the growth took in makes the front jut out in patches, one to three voxels
    at a time, where the deep layers' test (:func:`tissue_on_fascia`) sees too few layers. A
    patch wider than about half the window moves the median with it and is kept. Gland on the
    fascia and the muscle differ by little more than the noise, so the voxel holding both reads
    alike whichever it mostly is; where the fascia lies there is read from the lines around with
    fat in front, whose unmixed fractions place it (to about a tenth of a voxel, hence
    ``share``). Against fat the muscle's own fractions are the better estimate, so there only
    what lies a voxel or more in front goes."""
    m = grid.posterior_last(muscle)
    if not m.any():
        return np.zeros_like(muscle)
    p = grid.posterior_last(probability)
    first_index = muscle_front(m)[..., None]
    first = np.take_along_axis(p, first_index, axis=-1)[..., 0]
    before = np.where(first_index > 0, np.take_along_axis(p, np.maximum(first_index - 1, 0), axis=-1), 0.0)[..., 0]
    # a fraction that disagrees with the mask (a border moved after it was estimated) says nothing
    first = np.where((first >= 0.5) & (first <= 1.0), first, 1.0)
    before = np.where((before >= 0.0) & (before < 0.5), before, 0.0)
    position = first_index[..., 0] + (1.0 - first) - before  # in voxels from the line's anterior end
    across = [s for axis, s in enumerate(grid.spacing_zyx) if axis != grid.ap_axis]
    size = [max(1, int(round(window_mm / s))) for s in across]
    median = ndimage.median_filter(position, size=size, mode="nearest")
    gland_in_front = np.zeros_like(m)
    gland_in_front[..., 1:] = grid.posterior_last(glandular)[..., :-1]
    # to a fraction of a voxel: the local mean of the lines with fat in front near the median
    inlier = m.any(axis=-1) & ~np.take_along_axis(gland_in_front, first_index, axis=-1)[..., 0] \
        & (np.abs(position - median) <= 1.0)
    sigma = [local_mm / s for s in across]
    weight = ndimage.gaussian_filter(inlier.astype(float), sigma, mode="nearest")
    local = ndimage.gaussian_filter(np.where(inlier, position, 0.0), sigma, mode="nearest")
    fascia = np.where(weight > 0.05, local / np.maximum(weight, 1e-9), median)[..., None]
    index = np.arange(m.shape[-1])
    behind = np.clip(index + 1.0 - fascia, 0.0, 1.0)  # each voxel's share behind the fascia
    return grid.from_posterior_last(m & ((index + 2.0 <= median[..., None]) | ((behind <= share) & gland_in_front)))
