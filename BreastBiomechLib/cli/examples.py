"""Small hidden-effect cases made by the command line (``breastbiomech phantom`` and ``optimise``)
and fitted on the CPU in a couple of minutes: one set-up for the headless tests (Testing/) and the
Breast Discrepancy module's in-app self-test, so that the test a user runs in Slicer is the one
validated headless. Not a command: the command line's layer, since it runs commands.

- :func:`small_friction_case`: a 400 cm^3 phantom (2 x 2 x 4 mm voxels, 8 mm truth mesh)
  compressed 40 % with plate friction mu = 1 hidden in its truth, copied without its truth
  files and fitted without friction on a 12 mm mesh (:func:`fit_coarse`).

Frames and units: LPS millimetres.
"""

from __future__ import annotations

import shutil
from pathlib import Path

FIT = ["--model", "iso-hetero", "--free", "E", "--optimiser", "cmaes", "--budget", "12", "--population", "6",
       "--tolerance-mm", "0.05", "--quiet"]  # the coarse fit's settings (12 CMA-ES solves)


def without_truth(case: Path, into: Path) -> Path:
    """A copy of the compressed case ``case`` in ``into`` without its truth files (what a
    diagnosis may read)."""
    from BreastBiomechLib.phantom.truth_files import TRUTH_MESH, TRUTH_RECORD, truth_folder

    copy = Path(shutil.copytree(case, into))
    for name in (TRUTH_RECORD, TRUTH_MESH):
        (truth_folder(copy) / name).unlink()
    return copy


def fit_coarse(case: Path, out: Path, edge_mm: float = 10.0, device: str = "cpu") -> Path:
    """``breastbiomech optimise`` (iso-hetero, E free, 12 CMA-ES solves) of ``case`` into ``out``
    on ``device``, with an ``edge_mm`` fitting mesh of its labels without interface refinement
    and a surface of half that edge (the diagnosis compares the skin)."""
    from BreastBiomechLib.cli import main  # imported when run: the entry point imports this module's siblings
    from BreastBiomechLib.io.images import read_image
    from BreastBiomechLib.io.meshes import write_vtu
    from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels

    out = Path(out)
    mesh = mesh_labels(read_image(Path(case) / "labels.nrrd"), MeshSettings(edge_mm=edge_mm,
                                                                              surface_edge_mm=edge_mm / 2,
                                                                              refine_interfaces=False)).mesh
    mesh_file = out.parent / f"{out.name}-mesh.vtu"
    write_vtu(mesh_file, mesh)
    if main(["optimise", str(case), "--out", str(out), "--mesh", str(mesh_file), *FIT, "--device", device]) != 0:
        raise RuntimeError(f"the coarse fit of {case} failed (see the messages above)")
    return out


def small_friction_case(root: Path, device: str = "cpu") -> tuple[Path, Path]:
    """(case, fit) of the small hidden-friction case made in ``root`` (a new or empty folder):
    ``root/made`` the phantom with its truth, ``root/case`` the copy without it, ``root/fit``
    its coarse fit."""
    from BreastBiomechLib.cli import main

    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    if main(["phantom", "--seed", "2", "--volume-cm3", "400", "--spacing", "2", "2", "4", "--compressed",
             "--compression", "0.4", "--truth-edge-mm", "8", "--device", device, "--no-overview", "--friction", "1.0",
             "--out", str(root / "made")]) != 0:
        raise RuntimeError("the small hidden-friction phantom could not be made (see the messages above)")
    case = without_truth(root / "made", root / "case")
    return case, fit_coarse(case, root / "fit", edge_mm=12.0, device=device)
