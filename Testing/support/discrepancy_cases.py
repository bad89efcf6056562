"""Small CPU cases for the discrepancy tests: a compressed case without its truth, and its fit."""

from __future__ import annotations

import shutil
from pathlib import Path

FIT = ["--model", "iso-hetero", "--free", "E", "--optimiser", "cmaes", "--budget", "12", "--population", "6",
       "--tolerance-mm", "0.05", "--device", "cpu", "--quiet"]


def without_truth(case: Path, into: Path) -> Path:
    """A copy of the compressed case ``case`` in ``into`` without its truth files."""
    copy = Path(shutil.copytree(case, into))
    for name in ("truth.json", "truth_mesh.vtu"):
        (copy / "compressed" / name).unlink()
    return copy


def fit_coarse(case: Path, out: Path, edge_mm: float = 10.0) -> Path:
    """``breastbiomech optimise`` (iso-hetero, E free, 12 CMA-ES solves, on the CPU) of ``case``
    into ``out``, with an ``edge_mm`` fitting mesh of its labels without interface refinement and
    a surface of half that edge (the diagnosis compares the skin)."""
    from BreastBiomechLib.cli import main
    from BreastBiomechLib.io.images import read_image
    from BreastBiomechLib.io.meshes import write_vtu
    from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels

    mesh = mesh_labels(read_image(case / "labels.nrrd"), MeshSettings(edge_mm=edge_mm,
                                                                        surface_edge_mm=edge_mm / 2,
                                                                        refine_interfaces=False)).mesh
    write_vtu(out.parent / f"{out.name}-mesh.vtu", mesh)
    assert main(["optimise", str(case), "--out", str(out), "--mesh", str(out.parent / f"{out.name}-mesh.vtu"), *FIT]) == 0
    return out
