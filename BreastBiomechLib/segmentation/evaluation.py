"""Agreement of a segmentation with a reference label map (the phantom's ground truth)."""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk

from BreastBiomechLib import labels as lt


def dice_per_tissue(labels: sitk.Image, reference: sitk.Image) -> dict[str, float]:
    """Dice coefficient 2|A and B| / (|A| + |B|) per tissue of the label table present in either
    map (1.0 when a tissue is in neither). Both maps must share one grid."""
    if labels.GetSize() != reference.GetSize():
        raise ValueError(f"label maps differ in size: {labels.GetSize()} vs {reference.GetSize()}")
    a, b = sitk.GetArrayViewFromImage(labels), sitk.GetArrayViewFromImage(reference)
    out = {}
    for t in lt.TISSUES:
        x, y = a == t.label, b == t.label
        total = int(np.count_nonzero(x)) + int(np.count_nonzero(y))
        if total:
            out[t.name] = 2.0 * int(np.count_nonzero(x & y)) / total
    return out
