"""A phantom case on disk: NRRD images, a Slicer point list, parameters.json and overview.png.

Layout of a case folder::

    mr.nrrd                 MR volume (float32)
    labels.nrrd             tissue labels (uint8, the label table of BreastBiomechLib.labels)
    fraction_<tissue>.nrrd  partial-volume fraction per tissue (float32, 0-1)
    bias_field.nrrd         the multiplicative bias field applied to mr.nrrd
    signal.nrrd             the MR before bias and noise (what deformed cases are warped from)
    landmarks.mrk.json      17 landmarks (LPS), loadable in Slicer
    seeds_muscle.mrk.json   4 seed points on the pectoral muscle (for `breastbiomech segment`)
    seeds_tumour.mrk.json   3 seed points in the tumour, when there is one
    parameters.json         every generating parameter, and the measured summary
    overview.png            three orthogonal slices with label contours and landmarks
"""

from __future__ import annotations

import json
from pathlib import Path

from BreastBiomechLib.io.atomic import write_text_atomically
from BreastBiomechLib.io.case_layout import CaseLayout
from BreastBiomechLib.io.images import read_image, write_image
from BreastBiomechLib.io.markups import read_markups, write_markups
from BreastBiomechLib.phantom.generate import PhantomCase
from BreastBiomechLib.phantom.parameters import PhantomParameters
from BreastBiomechLib.phantom.seeds import seed_points

SEED_COUNTS = {"muscle": 4, "tumour": 3}  # seed points written per seeded tissue


def write_phantom(case: PhantomCase, out_dir: str | Path, overview: bool = True) -> dict[str, Path]:
    """Write ``case`` into ``out_dir`` (created if needed); returns the written paths by role."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    layout = CaseLayout(out)
    paths = {
        "mr": write_image(layout.mr, case.image),
        "labels": write_image(layout.truth_labels, case.labels),
        "bias_field": write_image(out / "bias_field.nrrd", case.bias_field),
        **({"signal": write_image(out / "signal.nrrd", case.signal)} if case.signal is not None else {}),
        "landmarks": write_markups(layout.landmarks, case.landmarks, name="Landmarks"),
    }
    for name, image in case.fractions.items():
        paths[f"fraction_{name}"] = write_image(out / f"fraction_{name}.nrrd", image)
    for tissue, count in SEED_COUNTS.items():
        if case.summary["tissue_volumes_cm3"].get(tissue, 0.0) > 0:
            seeds = seed_points(case.labels, tissue, count)
            where = {"muscle": layout.seeds_muscle, "tumour": layout.seeds_tumour}[tissue]
            paths[f"seeds_{tissue}"] = write_markups(where, seeds, name=f"Seeds {tissue}")
    document = {"parameters": case.parameters.to_dict(), "summary": case.summary}
    paths["parameters"] = out / "parameters.json"
    write_text_atomically(paths["parameters"], json.dumps(document, indent=2) + "\n")
    if overview:
        from BreastBiomechLib.visualisation import save_overview

        paths["overview"] = save_overview(
            out / "overview.png", case.image, case.labels, case.landmarks,
            title=f"Breast phantom, seed {case.parameters.seed}: "
                  f"{case.summary['breast_volume_cm3']:.0f} cm³, "
                  f"density {case.summary['glandular_density']:.0%}",
        )
    return paths


def read_phantom(case_dir: str | Path) -> PhantomCase:
    """Read a case folder written by :func:`write_phantom`."""
    folder = Path(case_dir)
    layout = CaseLayout(folder)
    if not (folder / "parameters.json").is_file():
        raise FileNotFoundError(f"{folder}: not a phantom case folder (no parameters.json); "
                                "make one with `breastbiomech phantom --out DIR`")
    document = json.loads((folder / "parameters.json").read_text())
    params = PhantomParameters.from_dict(document["parameters"])
    fractions = {p.name[len("fraction_"):-len(".nrrd")]: read_image(p) for p in sorted(folder.glob("fraction_*.nrrd"))}
    return PhantomCase(
        parameters=params,
        image=read_image(layout.mr),
        labels=read_image(layout.truth_labels),
        fractions=fractions,
        bias_field=read_image(folder / "bias_field.nrrd"),
        landmarks=read_markups(layout.landmarks),
        summary=document["summary"],
        signal=read_image(folder / "signal.nrrd") if (folder / "signal.nrrd").is_file() else None,
    )
