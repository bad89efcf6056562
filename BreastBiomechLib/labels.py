"""The one tissue label table used everywhere: label images, segment names, colours, meshes.

Label values are the voxel values of every label image the library reads or writes and the
``tissue`` cell array of every mesh. ``0`` is background (air, and anything posterior to the
pectoral muscle that is not modelled).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Tissue:
    """One tissue class: its label value, name (also the segment name in Slicer) and colour."""

    label: int
    name: str
    color: tuple[float, float, float]  # RGB in [0, 1], used for segments and overview pictures


BACKGROUND = 0
FAT = Tissue(1, "fat", (0.93, 0.82, 0.55))
GLANDULAR = Tissue(2, "glandular", (0.86, 0.38, 0.42))
MUSCLE = Tissue(3, "muscle", (0.55, 0.18, 0.20))
TUMOUR = Tissue(4, "tumour", (0.25, 0.50, 0.95))
SKIN = Tissue(5, "skin", (0.98, 0.72, 0.60))

TISSUES: tuple[Tissue, ...] = (FAT, GLANDULAR, MUSCLE, TUMOUR, SKIN)
BY_LABEL: dict[int, Tissue] = {t.label: t for t in TISSUES}
BY_NAME: dict[str, Tissue] = {t.name: t for t in TISSUES}


def tissue(key: int | str) -> Tissue:
    """Look a tissue up by label value or name; a clear error names the valid choices."""
    table = BY_LABEL if isinstance(key, int) else BY_NAME
    try:
        return table[key]
    except KeyError:
        choices = ", ".join(f"{t.label}={t.name}" for t in TISSUES)
        raise KeyError(f"unknown tissue {key!r}; the label table has {choices}") from None


def present_labels(values) -> list[int]:
    """The tissue labels present among a label map's voxel ``values`` (integers), in order.
    ValueError when none is (all background) or when a value is outside the label table."""
    present = [int(v) for v in np.unique(values) if v != BACKGROUND]
    if not present:
        raise ValueError("the label map has no labelled voxels (all background); segment the breast first")
    unknown = [v for v in present if v not in BY_LABEL]
    if unknown:
        raise ValueError(f"the label map holds values {unknown[:8]} outside the label table "
                         f"({', '.join(f'{t.label}={t.name}' for t in TISSUES)}); relabel it to those values")
    return present
