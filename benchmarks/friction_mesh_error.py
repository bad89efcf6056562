"""How much a fitting mesh's own error outweighs friction above sticking (issue 77's ladder).

A compressed phantom made by ``breastbiomech phantom --compressed --friction MU`` holds its
truth (``compressed/truth.json``, the truth mesh and the truth's landmarks). This solves the
truth's compression again with the truth's own materials and each friction coefficient of
``--mu``, on the truth mesh (``--mesh truth``) or on a mesh of the truth's labels at an element
size (``--mesh 6``: the geometry and tissues the truth had, only coarser), and prints one JSON
line per coefficient: the mean, RMS and largest distance (mm) of the landmarks it predicts from
the truth's. On the truth mesh the truth's mu gives 0; above sticking the other coefficients
differ from it by the friction signal alone; on a coarser mesh every coefficient differs by the
mesh's own error besides (docs/discrepancy.md, "Why friction refits below its truth").

    python benchmarks/friction_mesh_error.py CASE --mesh truth --mu 0.6 0.15 0.3 1.0 1.5
    python benchmarks/friction_mesh_error.py CASE --mesh 6 --mu 0 0.2 0.3 0.6 1.0 1.5

Reads a phantom's truth on purpose (a diagnostic, never a fit). CPU by default (``--device``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def main() -> None:
    from BreastBiomechLib.io.images import read_image
    from BreastBiomechLib.io.markups import read_markups
    from BreastBiomechLib.io.meshes import read_vtu
    from BreastBiomechLib.landmarks.mapping import map_landmarks
    from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels
    from BreastBiomechLib.phantom.compressed import TruthModel, truth_case
    from BreastBiomechLib.solver.run_case import run_case

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("case", type=Path, help="a compressed phantom with its truth (breastbiomech phantom --compressed)")
    parser.add_argument("--mesh", default="truth", help="'truth' or an element size (mm) for a mesh of the truth labels")
    parser.add_argument("--mu", type=float, nargs="+", required=True, help="friction coefficients to solve")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()

    record = json.loads((args.case / "compressed" / "truth.json").read_text())["truth"]
    reference = read_markups(args.case / "landmarks.mrk.json")
    measured = read_markups(args.case / "compressed" / "landmarks.mrk.json")
    if args.mesh == "truth":
        mesh = read_vtu(args.case / "compressed" / "truth_mesh.vtu")
    else:
        mesh = mesh_labels(read_image(args.case / "labels.nrrd"), MeshSettings(edge_mm=float(args.mesh)),
                           nipple_mm=reference.position("nipple")).mesh
    names = [name for name in measured.labels if name in reference.labels]
    for mu in args.mu:
        started = time.perf_counter()
        truth = TruthModel(compression=record["compression"], axis=record["axis"], materials=record["materials"],
                           edge_mm=record["edge_mm"], moving_plate=record["moving_plate"],
                           chest_clearance_mm=record["chest_clearance_mm"], friction=mu)
        result = run_case(*truth_case(mesh, truth, args.device))
        predicted = map_landmarks(mesh, result.displacement, reference)
        errors = np.array([np.linalg.norm(predicted.position(n) - measured.position(n)) for n in names])
        print(json.dumps({"mesh": args.mesh, "tets": len(mesh.tets), "mu": mu, "mean_mm": round(float(errors.mean()), 4),
                          "rms_mm": round(float(np.sqrt(np.mean(errors ** 2))), 4),
                          "max_mm": round(float(errors.max()), 3), "status": result.solution.status,
                          "seconds": round(time.perf_counter() - started, 1)}), flush=True)


if __name__ == "__main__":
    main()
