"""``breastbiomech simulate``: solve a case file."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from BreastBiomechLib.cli.common import device_argument
from BreastBiomechLib.io.atomic import write_text_atomically
from BreastBiomechLib.io.cases import read_case
from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.solver.run_case import run_case


def cmd_simulate(args) -> int:
    """Solve CASE.json; write the mesh with its displacement and a JSON summary of the solve."""
    from BreastBiomechLib.io.meshes import write_vtu

    model, settings = read_case(args.case)
    settings = replace(settings, device=args.device or settings.device)
    mesh = model.mesh
    print(f"simulate {args.case}: {len(mesh.nodes)} nodes, {len(mesh.tets)} tets, {model.formulation}, "
          f"{settings.method}, device {settings.device or 'default'}")

    def report(fraction):
        print(f"\r  {fraction:6.1%} of the step budget", end="", file=sys.stderr, flush=True)

    def unloaded_report(iteration, residual):
        print(f"  unloaded shape: iteration {iteration}, largest node mismatch {residual:.4f} mm", file=sys.stderr)

    result = run_case(model, settings, progress=None if args.quiet else report,
                      reference_progress=None if args.quiet else unloaded_report)
    solution, model, reference_state = result.solution, result.model, result.reference_state
    if reference_state is not None:
        print(f"  unloaded reference state: {reference_state['iterations']} iterations, residual "
              f"{reference_state['residual_mm']:.3g} mm, largest gravity sag {reference_state['largest_sag_mm']:.2f} mm, "
              f"{reference_state['wall_s']:.1f} s")
    if not args.quiet:
        print(file=sys.stderr)
    out = Path(args.out)
    # displacements from the mesh as given (the imaged shape, also with a pre-stressed start)
    point_data = {**mesh.point_data, "displacement": result.displacement}
    if reference_state is not None:
        point_data["unloaded_displacement"] = result.unloaded_displacement
    deformed = TetMesh(mesh.nodes, mesh.tets, point_data=point_data, cell_data=dict(mesh.cell_data))
    mesh_path = write_vtu(out / "deformed.vtu", deformed)
    summary = {
        "status": solution.status, "message": solution.message, "steps": solution.steps,
        "time_step_s": solution.time_step, "wall_s": solution.wall_time,
        "ke_ie_at_end_of_loading": solution.ke_ie_at_end_of_loading,
        "estimated_error_mm": solution.estimated_error_mm, "stable_time_step_s": solution.stable_time_step,
        "max_displacement_mm": float(np.linalg.norm(point_data["displacement"], axis=1).max()),
        "reference_state": reference_state,
        "plates": {p.name: solution.plate_forces[i].tolist() for i, p in enumerate(model.loading.plates)},
        "plate_normal_forces": {p.name: float(solution.plate_normal_forces[i])
                                for i, p in enumerate(model.loading.plates)},
        "plate_tangential_forces": {p.name: solution.plate_tangential_forces[i].tolist()
                                    for i, p in enumerate(model.loading.plates)},
        "history": {key: np.asarray(value).tolist() for key, value in solution.history.items()},
        "supports": list(model.loading.notes),
        "units": "mm, N, J, s (plate forces: force of the plate on the tissue, LPS)",
    }
    write_text_atomically(out / "solution.json", json.dumps(summary, indent=1, allow_nan=True))
    print(f"{solution.status}: {solution.message}")
    print(f"  {solution.steps} steps in {solution.wall_time:.2f} s; max displacement "
          f"{summary['max_displacement_mm']:.2f} mm")
    for name, force in summary["plates"].items():
        print(f"  plate {name}: force {np.linalg.norm(force):.3f} N (normal {summary['plate_normal_forces'][name]:.3f} N, "
              f"tangential {np.linalg.norm(summary['plate_tangential_forces'][name]):.3f} N)")
    for note in model.loading.notes:
        print(f"  support: {note}")
    print(f"  written: {mesh_path} (point array 'displacement', mm) and {out / 'solution.json'}")
    return 0 if solution.ok else 1


def add_parsers(sub) -> None:
    """Register the ``simulate`` command on ``sub`` (argparse sub-parsers)."""
    p = sub.add_parser("simulate", help="solve a case file (mesh + materials + loading, see docs/solver.md)")
    p.add_argument("case", help="CASE.json")
    p.add_argument("--out", required=True, help="output folder for deformed.vtu and solution.json")
    p.add_argument("--device", type=device_argument, default=None, help="cuda, cpu or a warp device name (default: the case's, or warp's)")
    p.add_argument("--quiet", action="store_true", help="no progress on standard error")
    p.set_defaults(func=cmd_simulate)
