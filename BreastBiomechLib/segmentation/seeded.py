"""Seeded segmentation of structures that intensity alone does not separate from their
surroundings (pectoral muscle, tumour): confidence-connected region growing from the user's seed
points on the lightly smoothed volume, then a partial-volume refinement of the border.

Arrays in SimpleITK's (z, y, x) order; lengths in millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from BreastBiomechLib.segmentation.morphology import local_mean, seeded_components, smooth_trend
from BreastBiomechLib.segmentation.volume import VoxelGrid

_FACES = ndimage.generate_binary_structure(3, 1)


@dataclass
class GrowSettings:
    """``smoothing_mm``: Gaussian sigma of the smoothing before growing; ``multiplier``: a voxel
    joins when its smoothed intensity lies within this many noise standard deviations of the
    structure's local level; ``iterations``: re-estimates of that level from the grown region;
    ``trend_mm``: the scale over which the structure's level may change (a bias field's);
    ``seed_radius``: voxels around each seed that give the first estimate; ``level_mm``: the
    scale over which the intensities just inside and just outside the border are averaged;
    ``border_passes``: refinements of the border; ``border_smoothing_mm``: Gaussian sigma of the
    smoothing of the unmixed fractions before each decision (0: none). Unmixing one voxel at a
    time has a fraction noise of sigma / contrast (0.2-0.4 for a tumour against gland at SNR
    30-15), and each pass lets noise move the border outward; smoothing the fractions, not the
    intensities (which would blur a small structure's inside level), keeps a smooth border's
    half-level where it is."""

    smoothing_mm: float = 1.0
    multiplier: float = 3.0
    iterations: int = 5
    trend_mm: float = 15.0
    seed_radius: int = 1
    level_mm: float = 2.0
    border_passes: int = 2
    border_smoothing_mm: float = 0.0

    def __post_init__(self) -> None:
        if self.multiplier <= 0 or self.iterations < 1 or self.seed_radius < 0 or self.border_passes < 0:
            raise ValueError("region growing needs a positive multiplier, at least one iteration and "
                             "non-negative seed radius and border passes")
        if self.smoothing_mm < 0 or self.border_smoothing_mm < 0 or self.level_mm <= 0 or self.trend_mm <= 0:
            raise ValueError("smoothing, trend and level widths must be positive lengths (mm)")


@dataclass
class OutsideTissues:
    """The pure intensities ``levels`` (arrays on the grid or numbers, e.g. bias-corrected fat and
    glandular levels of an EM fit) of the tissues that may lie just outside a structure on the
    voxels of ``where``. ``reads``: what each tissue reads in the image where that differs from
    the signal it adds to a mixed voxel (air: the mean of its noise's magnitude, but no signal,
    level 0); by default its level."""

    levels: tuple[np.ndarray, ...]
    where: np.ndarray
    reads: tuple[np.ndarray, ...] | None = None


@dataclass
class Surroundings:
    """What may lie just outside a seeded structure, for unmixing its border voxels.

    ``empty``: voxels known to hold nothing (air outside the body; their intensity counts as
    0), so that a structure on the body surface, such as a muscle with no thorax imaged behind
    it, is unmixed against air. ``tissues``: pure levels to unmix against (:class:`OutsideTissues`);
    a border voxel in one's ``where`` is unmixed against the level nearest to the mean of its own
    outside neighbours, not against a local average of the outside layer: in textured tissue that
    average lies between fat and gland, and pure gland next to a tumour would read as
    two-thirds tumour; behind a muscle a fat plane thinner than a voxel has no pure voxel at all."""

    empty: np.ndarray | None = None
    tissues: tuple[OutsideTissues, ...] = ()


@dataclass
class SeededRegion:
    """A segmented structure: ``mask`` (bool); ``probability`` (float32, its volume fraction per
    voxel: 1 inside, 0 outside, the linear partial-volume estimate on the voxels either side of
    the border); ``inside_level``: the structure's local intensity on those voxels (0 elsewhere)."""

    mask: np.ndarray
    probability: np.ndarray
    inside_level: np.ndarray


def grow_from_seeds(array: np.ndarray, seeds: np.ndarray, within: np.ndarray, grid: VoxelGrid,
                    settings: GrowSettings | None = None,
                    surroundings: Surroundings | None = None) -> SeededRegion:
    """The structure holding the seed voxels ``seeds`` ((N, 3) indices (z, y, x), inside
    ``within``), grown inside ``within`` through voxels of similar intensity, under a bias field.

    Growing works on the volume smoothed by ``smoothing_mm``. The structure's level is a smooth
    field: first the seeds' levels spread over the volume, then, ``iterations`` times, the local
    mean (``trend_mm``) of the region grown so far. A voxel joins when it is connected to a seed
    and within ``multiplier`` noise standard deviations of the level, the noise measured as the
    spread about the level (seed neighbourhoods first, then the region). So a thin structure
    whose intensity drifts by tens of percent across the field of view (a pectoral muscle under
    a bias field) is followed, while a fixed intensity window would either stop short or leak.
    Cavities are filled; then the border refinement (:func:`border_fractions`, against
    ``surroundings``)."""
    settings = settings or GrowSettings()
    values = array.astype(np.float32)
    smooth = _smoothed(values, grid, settings)
    near = np.zeros(values.shape, bool)
    near[tuple(seeds.T)] = True
    if settings.seed_radius > 0:
        near = ndimage.binary_dilation(near, np.ones((2 * settings.seed_radius + 1,) * 3, bool))
    region = near & within
    level = smooth_trend(smooth, region, 4 * settings.trend_mm, grid.spacing_zyx)
    level[level == 0] = float(np.median(smooth[region]))
    labels, _ = ndimage.label(region)
    noise = float(np.sqrt(np.mean([smooth[labels == k].var() for k in range(1, labels.max() + 1)])))
    for _ in range(settings.iterations):
        accept = within & (np.abs(smooth - level) <= settings.multiplier * max(noise, 1e-6)) | near & within
        region = seeded_components(accept, seeds)
        local = smooth_trend(smooth, region, settings.trend_mm, grid.spacing_zyx)
        level = np.where(local > 0, local, level)
        residual = (smooth - level)[region]
        noise = 1.4826 * float(np.median(np.abs(residual - np.median(residual))))
    mask = seeded_components(ndimage.binary_fill_holes(region), seeds)
    return _refine(values, mask, within, seeds, grid, settings, surroundings)


def grow_to_midpoint(array: np.ndarray, seeds: np.ndarray, within: np.ndarray, grid: VoxelGrid,
                     surrounding_level, settings: GrowSettings | None = None,
                     surroundings: Surroundings | None = None) -> SeededRegion:
    """The structure holding the seed voxels ``seeds`` ((N, 3) indices (z, y, x), inside
    ``within``): the voxels connected to the seeds whose smoothed intensity lies on the
    structure's side of the midpoint between its level (the median smoothed intensity at the
    seeds) and ``surrounding_level`` (a number or an array on the grid, e.g. the bias-corrected
    glandular level the tumour sits in); then the border refinement of :func:`grow_from_seeds`
    against ``surroundings``.

    Suited to a small compact structure (a tumour) whose seed neighbourhoods are too few and
    too mixed for confidence-connected statistics."""
    settings = settings or GrowSettings()
    values = array.astype(np.float32)
    smooth = _smoothed(values, grid, settings)
    around = np.broadcast_to(np.asarray(surrounding_level, dtype=np.float32), values.shape)
    level = float(np.median(smooth[tuple(seeds.T)]))
    seed_around = float(np.median(around[tuple(seeds.T)]))
    if abs(level - seed_around) < 1e-3 * max(abs(seed_around), 1.0):
        raise ValueError("the seeded structure has the intensity of its surroundings: there is no "
                         "contrast to delineate it; move the seeds into the structure")
    midpoint = 0.5 * (level + around)
    side = (smooth < midpoint) if level < seed_around else (smooth > midpoint)
    mask = seeded_components(ndimage.binary_fill_holes(side & within), seeds)
    return _refine(values, mask, within, seeds, grid, settings, surroundings)


def _smoothed(values: np.ndarray, grid: VoxelGrid, settings: GrowSettings) -> np.ndarray:
    if settings.smoothing_mm <= 0:
        return values
    return ndimage.gaussian_filter(values, settings.smoothing_mm / grid.spacing_zyx, mode="nearest")


def refine_border(array: np.ndarray, mask: np.ndarray, within: np.ndarray, seeds: np.ndarray, grid: VoxelGrid,
                  settings: GrowSettings | None = None, surroundings: Surroundings | None = None,
                  passes: int | None = None) -> SeededRegion:
    """The structure ``mask`` (bool, holding the ``seeds`` voxels) with its border refined again,
    as :func:`grow_from_seeds` ends, against ``surroundings`` learnt after it was grown;
    ``passes``: refinements (default ``settings.border_passes``; 0 keeps the mask as given and
    only estimates its border's fractions)."""
    return _refine(array.astype(np.float32), mask, within, seeds, grid, settings or GrowSettings(), surroundings,
                   passes)


def _refine(values, mask, within, seeds, grid: VoxelGrid, settings: GrowSettings,
            surroundings: Surroundings | None = None, passes: int | None = None) -> SeededRegion:
    """``passes`` (default ``border_passes``) partial-volume refinements of ``mask``'s border (see
    :func:`border_fractions`), worked in its bounding box with room for the levels' blur; the
    fractions made to agree with the mask (:func:`agreeing_probability`)."""
    passes = settings.border_passes if passes is None else passes
    if not mask.any():
        raise ValueError("the seeds did not grow into a region: they sit on voxels unlike the "
                         "structure; place them well inside it")
    margin = np.ceil(3 * settings.level_mm / grid.spacing_zyx).astype(int) + 3
    hits = np.nonzero(mask)
    box = tuple(slice(max(int(h.min()) - m, 0), int(h.max()) + m + 1) for h, m in zip(hits, margin))
    local_seeds = seeds - np.array([b.start for b in box])
    around = _cropped(surroundings, box)
    local = values[box]
    estimate = _denoised(border_fractions(local, mask[box], within[box], grid, settings, around), grid, settings)
    for done in range(1, passes + 1):
        estimate.mask = seeded_components(ndimage.binary_fill_holes(estimate.probability >= 0.5) & within[box],
                                          local_seeds)
        estimate.probability = agreeing_probability(estimate.probability, estimate.mask)
        if done < passes:
            estimate = _denoised(border_fractions(local, estimate.mask, within[box], grid, settings, around), grid,
                                 settings)
    estimate.probability = agreeing_probability(estimate.probability, estimate.mask)
    out = SeededRegion(np.zeros(values.shape, bool), np.zeros(values.shape, np.float32),
                       np.zeros(values.shape, np.float32))
    out.mask[box], out.probability[box], out.inside_level[box] = estimate.mask, estimate.probability, estimate.inside_level
    return out


def _denoised(estimate: SeededRegion, grid: VoxelGrid, settings: GrowSettings) -> SeededRegion:
    """``estimate`` with its fractions smoothed by ``settings.border_smoothing_mm`` (none at 0)."""
    if settings.border_smoothing_mm > 0:
        estimate.probability = ndimage.gaussian_filter(estimate.probability, settings.border_smoothing_mm /
                                                       grid.spacing_zyx, mode="nearest").astype(np.float32)
    return estimate


def _cropped(surroundings: Surroundings | None, box) -> Surroundings | None:
    if surroundings is None:
        return None
    return Surroundings(None if surroundings.empty is None else surroundings.empty[box],
                        tuple(OutsideTissues(_crop_levels(t.levels, t.where.shape, box), t.where[box],
                                             _crop_levels(t.reads, t.where.shape, box))
                              for t in surroundings.tissues))


def _crop_levels(levels, shape, box):
    return None if levels is None else tuple(np.broadcast_to(level, shape)[box] for level in levels)


def agreeing_probability(probability: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``probability`` made to agree with ``mask``: at least one half inside it (a filled cavity,
    an edited-in voxel), at most one half outside (a dropped fragment, an edited-out voxel), so
    that the mask is always the probability's majority."""
    return np.where(mask, np.maximum(probability, 0.5), np.minimum(probability, 0.5)).astype(np.float32)


def border_fractions(values: np.ndarray, region: np.ndarray, within: np.ndarray, grid: VoxelGrid,
                     settings: GrowSettings | None = None, surroundings: Surroundings | None = None) -> SeededRegion:
    """Partial-volume fractions of ``region`` (its mask kept as given) on the voxels either side
    of its border: fraction = (I - outside) / (inside - outside), clipped to [0, 1], where
    ``inside`` is the local mean (``level_mm``) of the layer of region voxels just inside those
    and ``outside`` that of the layer of ``within`` voxels just outside: each side's own
    neighbours, so a thin structure with different tissues on its two faces is unmixed against
    the right one. ``surroundings`` adds air (its voxels count as intensity 0 in the outside
    layer) and pure tissue levels to unmix against (see :class:`Surroundings`). Where the levels
    do not differ the mask itself is the fraction."""
    settings = settings or GrowSettings()
    surroundings = surroundings or Surroundings()
    values = values.astype(np.float32, copy=False)
    empty = surroundings.empty if surroundings.empty is not None else np.zeros_like(region)
    grown = ndimage.binary_dilation(region, _FACES)
    core = ndimage.binary_erosion(region, _FACES)
    band = within & grown & ~core
    inner_layer = core & ~ndimage.binary_erosion(core, _FACES)
    outer_layer = (within | empty) & ndimage.binary_dilation(grown, _FACES) & ~grown
    outside_values = np.where(empty, 0.0, values).astype(np.float32)
    sigma = settings.level_mm / grid.spacing_zyx
    level_in = local_mean(values, inner_layer if inner_layer.any() else region, sigma)
    level_out = local_mean(outside_values, outer_layer, sigma)
    has_outside = local_mean(np.ones_like(values), outer_layer, sigma) > 0
    for tissues in surroundings.tissues:
        level_out = _nearest_level(outside_values, outer_layer, level_out, band & tissues.where, tissues.levels,
                                   tissues.reads)
    contrast = level_in - level_out
    usable = band & (level_in > 0) & has_outside & (level_out >= 0) & \
        (np.abs(contrast) > 1e-6 * max(float(np.abs(values).max()), 1.0))
    probability = core.astype(np.float32)
    probability[usable] = np.clip((values[usable] - level_out[usable]) / contrast[usable], 0.0, 1.0)
    probability[band & ~usable] = region[band & ~usable]
    return SeededRegion(region.copy(), probability, np.where(band, level_in, 0.0).astype(np.float32))


def _nearest_level(values: np.ndarray, outer_layer: np.ndarray, level_out: np.ndarray, where: np.ndarray,
                   levels: tuple[np.ndarray, ...], reads: tuple[np.ndarray, ...] | None = None) -> np.ndarray:
    """``level_out`` with, on the voxels of ``where``, the one of ``levels`` whose reading
    (``reads``, default the levels) is nearest to the mean of the voxel's own outside neighbours
    (the outer layer within one voxel)."""
    near = local_mean(values, outer_layer, 0.7)
    stacked = np.stack([np.broadcast_to(level, values.shape) for level in levels])
    read = stacked if reads is None else np.stack([np.broadcast_to(r, values.shape) for r in reads])
    choice = np.argmin(np.abs(read - near[None]), axis=0)[None]
    nearest = np.take_along_axis(stacked, choice, axis=0)[0]
    usable = where & (near > 0) & (np.take_along_axis(read, choice, axis=0)[0] > 0) & (nearest >= 0)
    return np.where(usable, nearest, level_out).astype(np.float32)
