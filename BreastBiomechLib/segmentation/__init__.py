"""Tissue classification of a breast MR volume (seed section 2.2.1): body mask, pectoral muscle
and tumour from seed points, fat / fibroglandular tissue by EM with an MRF prior and bias-field
correction, merged into one label map with per-class probabilities.

Start with :func:`segment_tissues`. Step by step (as the BreastSegmentation module does, with
edits in between): :func:`segment_muscle`, :func:`segment_tumour` (given the muscle mask) and
:func:`classify_tissues` (given the muscle and tumour masks)."""

from BreastBiomechLib.segmentation.em import EMResult, EMSettings, classify_fat_glandular
from BreastBiomechLib.segmentation.evaluation import dice_per_tissue
from BreastBiomechLib.segmentation.fascia import FasciaSettings, tissue_on_fascia
from BreastBiomechLib.segmentation.pipeline import (SegmentationSettings, StructureSegmentation, TissueSegmentation,
                                                    classify_tissues, segment_muscle, segment_tissues, segment_tumour)
from BreastBiomechLib.segmentation.seeded import GrowSettings, SeededRegion, grow_from_seeds

__all__ = ["EMResult", "EMSettings", "FasciaSettings", "GrowSettings", "SeededRegion", "SegmentationSettings", "StructureSegmentation",
           "TissueSegmentation", "classify_fat_glandular", "classify_tissues", "dice_per_tissue", "grow_from_seeds",
           "segment_muscle", "segment_tissues", "segment_tumour", "tissue_on_fascia"]
