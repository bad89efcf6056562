"""A tissue segmentation on disk.

Layout of the output folder::

    labels.nrrd                 uint8 label map (values of BreastBiomechLib.labels)
    probability_<tissue>.nrrd   float32 probability of each tissue per voxel (0-1)
    bias_field.nrrd             float32 multiplicative bias field estimated over the breast
    segmentation.json           volumes, EM fit, timings, settings (and Dice when a reference was given)
"""

from __future__ import annotations

import json
from pathlib import Path

from BreastBiomechLib.io.atomic import write_text_atomically
from BreastBiomechLib.io.images import write_image
from BreastBiomechLib.segmentation.pipeline import TissueSegmentation


def write_segmentation(result: TissueSegmentation, out_dir: str | Path, extra: dict | None = None) -> dict[str, Path]:
    """Write ``result`` into ``out_dir`` (created if needed); ``extra`` entries are added to
    segmentation.json. Returns the written paths by role."""
    out = Path(out_dir)
    paths = {"labels": write_image(out / "labels.nrrd", result.labels)}
    for name, image in result.probabilities.items():
        paths[f"probability_{name}"] = write_image(out / f"probability_{name}.nrrd", image)
    paths["bias_field"] = write_image(out / "bias_field.nrrd", result.bias_field)
    paths["summary"] = out / "segmentation.json"
    write_text_atomically(paths["summary"], json.dumps({**result.summary, **(extra or {})}, indent=2) + "\n")
    return paths
