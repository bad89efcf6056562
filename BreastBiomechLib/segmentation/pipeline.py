"""The whole tissue classification of seed section 2.2.1: body, pectoral muscle from seeds,
breast, tumour from seeds, fat / fibroglandular by EM with MRF and bias correction, merged into
one label map of the label table with per-class probability images.

Images in, images out (LPS mm geometry kept); seeds are LPS mm points.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from BreastBiomechLib import labels as lt
from BreastBiomechLib.segmentation.body import air_level, body_mask
from BreastBiomechLib.segmentation.breast import breast_mask, breast_surface, skin_depth, skin_layer
from BreastBiomechLib.segmentation.em import FAT, GLANDULAR, EMSettings, classify_fat_glandular
from BreastBiomechLib.segmentation.fascia import FasciaSettings, ahead_of_fascia, one_layer, tissue_on_fascia
from BreastBiomechLib.segmentation.morphology import ball, seeded_components
from BreastBiomechLib.segmentation.seeded import (GrowSettings, OutsideTissues, SeededRegion, Surroundings,
                                                  agreeing_probability,
                                                  border_fractions, grow_from_seeds, grow_to_midpoint, refine_border)
from BreastBiomechLib.segmentation.volume import VoxelGrid, check_volume, seed_voxels
from BreastBiomechLib.timing import staged

Progress = Callable[[float, str], None]


@dataclass
class SegmentationSettings:
    """``em``: the fat/glandular model; ``muscle`` and ``tumour``: region growing from seeds;
    ``skin_mm``: the outer layer of the breast labelled skin (then folded into fat unless
    ``keep_skin``), kept out of the EM fit because skin is neither fat nor glandular tissue;
    ``measure_skin``: deepen that layer to where the image shows the skin and its
    partial-volume voxels reaching (a skin 3 mm thick imaged with 2.5 mm slices reaches 4 mm);
    ``body_surface_fraction``: see :func:`body_mask`; ``fascia``: how tissue lying on the
    muscle with no fat plane between is told from it (:func:`tissue_on_fascia`, then
    :func:`ahead_of_fascia`; None: neither looked for)."""

    em: EMSettings = field(default_factory=EMSettings)
    muscle: GrowSettings = field(default_factory=GrowSettings)
    tumour: GrowSettings = field(default_factory=lambda: GrowSettings(multiplier=2.0, border_smoothing_mm=0.8))
    skin_mm: float = 3.0
    measure_skin: bool = True
    keep_skin: bool = False
    body_surface_fraction: float = 0.3
    fascia: FasciaSettings | None = field(default_factory=FasciaSettings)

    def __post_init__(self) -> None:
        if not 0 <= self.skin_mm <= 10:
            raise ValueError("the skin layer must be 0-10 mm thick")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class TissueSegmentation:
    """``labels``: uint8 label map (label table values; 0 background, which includes the thorax
    behind the pectoral muscle); ``probabilities``: tissue name -> float32 image of the tissue's
    probability per voxel (fat and glandular: EM posteriors; muscle and tumour: partial-volume
    fractions across their borders; at most 1 in sum, the rest is background);
    ``bias_field``: the multiplicative bias estimated over the breast (1 elsewhere);
    ``summary``: volumes, EM fit, timings."""

    labels: sitk.Image
    probabilities: dict[str, sitk.Image]
    bias_field: sitk.Image
    summary: dict


@staged("segmentation")
def segment_tissues(image: sitk.Image, muscle_seeds, tumour_seeds=None,
                    settings: SegmentationSettings | None = None,
                    progress: Progress | None = None) -> TissueSegmentation:
    """Segment an MR volume from seed points (LPS mm) on the pectoral muscle (3-5 spread over it
    are enough) and, if there is a tumour, on the tumour (1-3). Deterministic."""
    settings = settings or SegmentationSettings()
    report = progress or (lambda fraction, message: None)
    grid = check_volume(image)
    array = sitk.GetArrayFromImage(image).astype(np.float32)
    seconds = {}
    started = time.perf_counter()
    report(0.0, "body")
    body = body_mask(array, grid, surface_fraction=settings.body_surface_fraction)
    seconds["body"] = time.perf_counter() - started
    report(0.1, "pectoral muscle from seeds")
    started = time.perf_counter()
    muscle = _grow_muscle(grid, array, body, muscle_seeds, settings)
    seconds["muscle"] = time.perf_counter() - started
    tumour, regions = None, None
    if tumour_seeds is not None and len(tumour_seeds):
        report(0.2, "tumour from seeds")
        started = time.perf_counter()
        regions = _breast_and_skin(grid, array, body, muscle.mask, settings)
        tumour = _grow_tumour(grid, array, muscle, *regions[:2], tumour_seeds, settings)
        seconds["tumour"] = time.perf_counter() - started
    result = _classify(grid, array, body, muscle, tumour, settings,
                       lambda f, m: report(0.4 + 0.6 * f, m), regions)
    result.summary["seconds"] = {**{k: round(v, 2) for k, v in seconds.items()}, **result.summary["seconds"]}
    result.summary["seeds"] = {"muscle": int(len(muscle_seeds)),
                               "tumour": 0 if tumour_seeds is None else int(len(tumour_seeds))}
    return result


def _grow_muscle(grid: VoxelGrid, array: np.ndarray, body: np.ndarray, seeds,
                 settings: SegmentationSettings) -> SeededRegion:
    """The pectoral muscle grown from its seeds, its border unmixed against air where it lies on
    the body surface (no thorax imaged behind it); then, once the breast in front of it is
    known, its border unmixed again against pure levels from a first fat/glandular fit: in
    front the fat or gland its outside neighbours show, behind it the fat of the subpectoral
    plane (thinner than a voxel at 1.5 mm, so no voxel of that plane is pure fat) or, with no
    thorax imaged, the air that the body's surface rule took in (its noise reads about a quarter
    of muscle at SNR 15, and against fat every such voxel unmixed to pure muscle). Tissue lying
    on the fascia with no fat plane between, which the growth takes in (gland is within three
    noise deviations of muscle at low SNR), is given back to the breast (:func:`tissue_on_fascia`
    for slabs several voxels deep, :func:`ahead_of_fascia` for patches jutting out of the
    muscle's smooth front), and the muscle made one layer along every anterior-posterior line
    (:func:`one_layer`: a film over breast tissue goes back to the breast, cavities open to the
    side are filled, so that no body voxel is left between the breast and the muscle with
    neither); the new border's fractions are then estimated without moving it again (one
    voxel's unmixing against the glandular level is noisier than the layer average that found
    it)."""
    seed_index = seed_voxels(grid, seeds, body, "pectoral muscle", "inside the body")
    muscle = grow_from_seeds(array, seed_index, body, grid, settings.muscle, Surroundings(empty=~body))
    breast, skin, _ = _breast_and_skin(grid, array, body, muscle.mask, settings)
    if not (breast & ~skin).any():
        return muscle
    fat, glandular = _fat_glandular_levels(grid, array, breast, skin, settings, muscle)
    front = ndimage.binary_dilation(breast)
    near_air = ndimage.binary_dilation(~body, ball(grid.spacing_zyx, 3.0))
    behind = body & ~front
    surroundings = Surroundings(empty=~body, tissues=(
        OutsideTissues((fat, glandular), front), OutsideTissues((fat,), behind & ~near_air),
        OutsideTissues((fat, 0.0), behind & near_air, reads=(fat, air_level(array, body, grid)))))
    muscle = refine_border(array, muscle.mask, body, seed_index, grid, settings.muscle, surroundings)
    mask = muscle.mask
    if settings.fascia is not None:
        mask = mask & ~tissue_on_fascia(array, mask, breast_mask(body, mask, grid), glandular, grid, settings.fascia)
        # gland in front: beneath the skin, at least three quarters glandular (a voxel of fat with
        # the muscle's partial volume below one half reads no darker than half of both)
        gland = body & ~skin & ~near_air & (array < glandular + 0.25 * (fat - glandular))
        mask = mask & ~ahead_of_fascia(mask, muscle.probability, gland, grid)
    mask = one_layer(mask, body, grid)
    if np.array_equal(mask, muscle.mask):
        return muscle
    mask = seeded_components(mask, seed_index)
    return refine_border(array, mask, body, seed_index, grid, settings.muscle, surroundings, passes=0)


def _fat_glandular_levels(grid: VoxelGrid, array: np.ndarray, breast: np.ndarray, skin: np.ndarray,
                          settings: SegmentationSettings, *regions: SeededRegion | None) -> tuple[np.ndarray, np.ndarray]:
    """The bias-corrected fat and glandular intensities over the volume, from a first
    fat/glandular fit of the breast without its skin layer (a tumour counted as glandular)."""
    em = classify_fat_glandular(_unmixed(array, breast, *regions), breast & ~skin, grid.spacing_zyx, settings.em)
    return em.means[FAT] * em.bias_field, em.means[GLANDULAR] * em.bias_field


def _breast_and_skin(grid: VoxelGrid, array: np.ndarray, body: np.ndarray, muscle_mask: np.ndarray,
                     settings: SegmentationSettings) -> tuple[np.ndarray, np.ndarray, float]:
    """The breast in front of the muscle (its surface placed for its outermost tissue,
    :func:`breast_surface`), its outer skin layer (both independent of the tumour)
    and that layer's thickness (mm): ``settings.skin_mm``, or deeper where the image shows the
    skin reaching deeper (:func:`skin_depth`) when ``settings.measure_skin``."""
    breast = breast_mask(body, muscle_mask, grid)
    body = breast_surface(array, body, breast, grid)
    breast = breast_mask(body, muscle_mask, grid)
    thickness = settings.skin_mm
    if settings.measure_skin:
        thickness = max(thickness, skin_depth(array, body, breast, grid))
    return breast, skin_layer(body, breast, grid, thickness, muscle_mask), thickness


def _grow_tumour(grid: VoxelGrid, array: np.ndarray, muscle: SeededRegion, breast: np.ndarray, skin: np.ndarray,
                 seeds, settings: SegmentationSettings) -> SeededRegion:
    """The tumour, delineated against the glandular tissue it sits in: a first fat/glandular fit
    of the breast (tumour included, as glandular) gives the bias-corrected glandular level at
    every voxel, and the tumour is what is connected to the seeds on the tumour's side of the
    midpoint between its level and that one; its border voxels are unmixed against the fat or
    glandular level, whichever their outside neighbours show."""
    seed_index = seed_voxels(grid, seeds, breast, "tumour", "inside the breast (anterior to the pectoral muscle)")
    fat, glandular = _fat_glandular_levels(grid, array, breast, skin, settings, muscle)
    return grow_to_midpoint(array, seed_index, breast, grid, glandular, settings.tumour,
                            Surroundings(tissues=(OutsideTissues((fat, glandular), breast),)))


@dataclass
class StructureSegmentation:
    """One seeded structure on the volume's grid: ``mask`` (uint8 image, 1 inside) and
    ``probability`` (float32 image: its volume fraction per voxel, see :class:`SeededRegion`)."""

    mask: sitk.Image
    probability: sitk.Image


def segment_muscle(image: sitk.Image, seeds, settings: SegmentationSettings | None = None) -> StructureSegmentation:
    """The pectoral muscle alone, from seed points (LPS mm) on it: the first step of
    :func:`segment_tissues`, for interactive use (inspect, edit, then go on)."""
    settings = settings or SegmentationSettings()
    grid = check_volume(image)
    array = sitk.GetArrayFromImage(image).astype(np.float32)
    muscle = _grow_muscle(grid, array, body_mask(array, grid, surface_fraction=settings.body_surface_fraction),
                          seeds, settings)
    return StructureSegmentation(grid.to_image(muscle.mask.astype(np.uint8)), grid.to_image(muscle.probability))


def segment_tumour(image: sitk.Image, muscle: sitk.Image, seeds,
                   settings: SegmentationSettings | None = None) -> StructureSegmentation:
    """The tumour alone, from seed points (LPS mm) in it, given the pectoral muscle mask (which
    delimits the breast; e.g. the edited result of :func:`segment_muscle`)."""
    settings = settings or SegmentationSettings()
    grid = check_volume(image)
    array = sitk.GetArrayFromImage(image).astype(np.float32)
    body, muscle_region, _ = _regions_from_masks(grid, image, array, muscle, None, settings)
    tumour = _grow_tumour(grid, array, muscle_region, *_breast_and_skin(grid, array, body, muscle_region.mask, settings)[:2],
                          seeds, settings)
    return StructureSegmentation(grid.to_image(tumour.mask.astype(np.uint8)), grid.to_image(tumour.probability))


def classify_tissues(image: sitk.Image, muscle: sitk.Image, tumour: sitk.Image | None = None,
                     settings: SegmentationSettings | None = None,
                     progress: Progress | None = None) -> TissueSegmentation:
    """The fat / glandular classification and the merged label map, given masks of the pectoral
    muscle and the tumour (non-zero voxels; e.g. edited in Slicer's Segment Editor) on the
    image's grid."""
    settings = settings or SegmentationSettings()
    grid = check_volume(image)
    array = sitk.GetArrayFromImage(image).astype(np.float32)
    body, muscle_region, tumour_region = _regions_from_masks(grid, image, array, muscle, tumour, settings)
    return _classify(grid, array, body, muscle_region, tumour_region, settings,
                     progress or (lambda fraction, message: None))


def _regions_from_masks(grid: VoxelGrid, image: sitk.Image, array: np.ndarray, muscle: sitk.Image,
                        tumour: sitk.Image | None, settings: SegmentationSettings):
    """The body, and the muscle and tumour masks as regions with partial-volume borders that
    agree with the masks as given."""
    masks = {}
    for name, mask in (("muscle", muscle), ("tumour", tumour)):
        if mask is not None:
            _check_same_grid(image, mask, name)
            masks[name] = sitk.GetArrayFromImage(mask) != 0
    if "muscle" not in masks or not masks["muscle"].any():
        raise ValueError("the pectoral muscle mask is empty: the breast is delimited by it, so "
                         "segment the muscle before the tumour and the fat and glandular tissue")
    body = body_mask(array, grid, surface_fraction=settings.body_surface_fraction) | masks["muscle"]
    regions = []
    for name, within in (("muscle", body), ("tumour", None)):
        if not masks.get(name, np.zeros(1, bool)).any():
            regions.append(None)
            continue
        if within is None:
            within = breast_mask(body, masks["muscle"], grid)
        region = border_fractions(array, masks[name], within, grid, getattr(settings, name),
                                  Surroundings(empty=~body) if name == "muscle" else None)
        region.probability = agreeing_probability(region.probability, region.mask)
        regions.append(region)
    return body, regions[0], regions[1]


def _check_same_grid(image: sitk.Image, mask: sitk.Image, name: str) -> None:
    same = (mask.GetSize() == image.GetSize()
            and np.allclose(mask.GetOrigin(), image.GetOrigin(), atol=1e-3)
            and np.allclose(mask.GetSpacing(), image.GetSpacing(), rtol=1e-5)
            and np.allclose(mask.GetDirection(), image.GetDirection(), atol=1e-5))
    if not same:
        raise ValueError(f"the {name} mask is not on the MR volume's grid (size {mask.GetSize()} vs "
                         f"{image.GetSize()}); resample it onto the volume first")


def _classify(grid: VoxelGrid, array: np.ndarray, body: np.ndarray, muscle: SeededRegion,
              tumour: SeededRegion | None, settings: SegmentationSettings, report: Progress,
              regions: tuple[np.ndarray, np.ndarray, float] | None = None) -> TissueSegmentation:
    """Fat/glandular fit and merging; ``regions``: the breast, skin layer and its thickness when already made."""
    started = time.perf_counter()
    report(0.0, "breast region")
    breast, skin, skin_mm = regions or _breast_and_skin(grid, array, body, muscle.mask, settings)
    tumour_mask = tumour.mask & breast if tumour is not None else np.zeros_like(breast)
    skin = skin & ~tumour_mask
    em_region = breast & ~skin & ~tumour_mask
    if not em_region.any():
        raise ValueError("the breast region is empty: check that the muscle seeds sit on the pectoral "
                         "muscle and not on the breast tissue in front of it")
    seconds = {"breast": time.perf_counter() - started}
    started = time.perf_counter()
    em = classify_fat_glandular(_unmixed(array, breast, muscle, tumour), em_region, grid.spacing_zyx, settings.em,
                                lambda f, m: report(0.05 + 0.85 * f, m))
    seconds["fat_glandular"] = time.perf_counter() - started

    report(0.9, "merging the tissue map")
    glandular = em_region & (em.probabilities[GLANDULAR] > 0.5)
    labels = np.zeros(array.shape, dtype=np.uint8)
    labels[breast] = lt.FAT.label
    labels[glandular] = lt.GLANDULAR.label
    labels[skin] = lt.SKIN.label if settings.keep_skin else lt.FAT.label
    labels[tumour_mask] = lt.TUMOUR.label
    labels[muscle.mask] = lt.MUSCLE.label

    # probabilities: seeded structures as fractions, the rest of the breast shared by the EM
    p_muscle = muscle.probability * body
    p_tumour = (tumour.probability * breast) if tumour is not None else np.zeros_like(p_muscle)
    free = np.clip(1.0 - p_muscle - p_tumour, 0.0, 1.0) * breast
    p_skin = free * skin
    probabilities = {
        "fat": free * np.where(em_region, em.probabilities[FAT], 0.0) + (0.0 if settings.keep_skin else p_skin),
        "glandular": free * np.where(em_region, em.probabilities[GLANDULAR], 0.0),
        "muscle": p_muscle,
        "tumour": p_tumour,
    }
    if settings.keep_skin:
        probabilities["skin"] = p_skin
    voxel_cm3 = float(np.prod(grid.spacing)) / 1000.0
    volumes = {t.name: float(np.count_nonzero(labels == t.label) * voxel_cm3) for t in lt.TISSUES
               if t.name in probabilities}
    breast_cm3 = sum(v for name, v in volumes.items() if name != "muscle")
    summary = {
        "tissue_volumes_cm3": volumes,
        "breast_volume_cm3": breast_cm3,
        "glandular_density": volumes["glandular"] / breast_cm3 if breast_cm3 else 0.0,
        "skin_layer_mm": float(skin_mm),
        "em": {"iterations": em.iterations, "converged": em.converged,
               "class_means": {"fat": float(em.means[FAT]), "glandular": float(em.means[GLANDULAR])},
               "class_log_sigmas": {"fat": float(em.sigmas[FAT]), "glandular": float(em.sigmas[GLANDULAR])},
               "bias_range": [float(em.bias_field[em_region].min()), float(em.bias_field[em_region].max())]},
        "settings": settings.to_dict(),
        "seconds": {k: round(v, 2) for k, v in seconds.items()},
    }
    report(1.0, "done")
    return TissueSegmentation(
        labels=grid.to_image(labels),
        probabilities={name: grid.to_image(p.astype(np.float32)) for name, p in probabilities.items()},
        bias_field=grid.to_image(np.where(breast, em.bias_field, 1.0).astype(np.float32)),
        summary=summary,
    )


def _unmixed(array: np.ndarray, breast: np.ndarray, *regions: SeededRegion | None) -> np.ndarray:
    """The intensities of the breast voxels along the muscle and tumour borders with the
    structure's share removed (I - p L) / (1 - p), p its fraction and L its local intensity, so
    that a voxel two-thirds fat and one-third muscle is classified as the fat it mostly is."""
    out = array.copy()
    for region in regions:
        if region is None:
            continue
        band = breast & ~region.mask & (region.probability > 0) & (region.probability < 0.5)
        p = region.probability[band]
        out[band] = np.maximum((array[band] - p * region.inside_level[band]) / (1.0 - p), 0.0)
    return out
