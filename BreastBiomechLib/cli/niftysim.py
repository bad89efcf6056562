"""``breastbiomech niftysim export|run``: a case as a NiftySim model, and a NiftySim model solved here."""

from __future__ import annotations

import json
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from BreastBiomechLib.cli.common import device_argument
from BreastBiomechLib.io.atomic import write_text_atomically
from BreastBiomechLib.io.cases import read_case
from BreastBiomechLib.mesh.tetmesh import TetMesh


def export_for_niftysim(path: Path, model, solved_displacement=None, formulation: str | None = None):
    """Write ``model`` for NiftySim the way the commands do: the settling phase dropped, a T4ANP
    model of several materials written as NiftySim's T4ANP (pressure averaged across materials),
    ``formulation`` (T4/T4ANP) if given; returns the path and the notes saying how the file
    differs from the model (also in the file's first comment)."""
    from BreastBiomechLib.io.niftysim import NiftySimExportWarning, differs_in_niftysim_anp, write_niftysim

    notes = []
    if formulation is not None and formulation != model.formulation:
        notes.append(f"formulation {formulation} instead of the case's {model.formulation}")
        model = replace(model, formulation=formulation)
    if differs_in_niftysim_anp(model):
        notes.append("NiftySim's T4ANP averages nodal pressure across materials, the case per material: this file is "
                     "NiftySim's model, which can invert at stiff/soft interfaces where the case's does not (run it "
                     "here first with `breastbiomech niftysim run`, or export with --formulation T4)")
        model = replace(model, anp_across_materials=True)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", NiftySimExportWarning)
        written = write_niftysim(path, model, drop_settling=True, solved_displacement=solved_displacement)
    notes += [str(w.message) for w in caught if issubclass(w.category, NiftySimExportWarning)]
    return written, notes


def cmd_export(args) -> int:
    """Write CASE.json as a NiftySim model (ContactPlates, or the solved displacements of
    ``--solved``'s deformed mesh for NiftySim's CPU build)."""
    from BreastBiomechLib.io.meshes import read_vtu

    model, _ = read_case(args.case)
    solved = None
    if args.solved:
        deformed = read_vtu(args.solved)
        if "displacement" not in deformed.point_data or len(deformed.nodes) != len(model.mesh.nodes):
            raise ValueError(f"{args.solved}: not this case's solution (a deformed.vtu of `breastbiomech simulate "
                             f"{args.case}` with a 'displacement' point array on its {len(model.mesh.nodes)} nodes)")
        solved = deformed.point_data["displacement"]
    path, notes = export_for_niftysim(Path(args.out), model, solved, args.formulation)
    print(f"NiftySim model written to {path} ({'solved displacements: any NiftySim build' if solved is not None else 'ContactPlates: NiftySim GPU build'})")
    for note in notes:
        print(f"  note: {note}")
    return 0


def cmd_run(args) -> int:
    """Read MODEL.xml as NiftySim runs it and solve it in physical time; write the deformed mesh
    (``displacement`` point array, as NiftySim's ``-export-mesh``) and a JSON summary."""
    from BreastBiomechLib.io.meshes import write_vtu
    from BreastBiomechLib.io.niftysim import NiftySimImportWarning, read_niftysim
    from BreastBiomechLib.solver import solve

    out = Path(args.out)
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out} exists and is not empty; choose a new output folder")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", NiftySimImportWarning)
        model = read_niftysim(args.model)
    for w in caught:
        print(f"  note: {w.message}")
    mesh = model.mesh
    print(f"niftysim run {args.model}: {len(mesh.nodes)} nodes, {len(mesh.tets)} tets, {model.formulation}, "
          f"time step {model.time_step:.3g} s, total time {model.loading.total_time:g} s")
    solution = solve(model, device=args.device, progress=None if args.quiet else lambda f: print(
        f"\r  {f:6.1%} of the steps", end="", file=sys.stderr, flush=True))
    if not args.quiet:
        print(file=sys.stderr)
    deformed = TetMesh(mesh.nodes, mesh.tets, point_data={"displacement": solution.displacement},
                       cell_data=dict(mesh.cell_data))
    write_vtu(out / "deformed.vtu", deformed)
    summary = {"status": solution.status, "message": solution.message, "steps": solution.steps,
               "time_step_s": solution.time_step, "wall_s": solution.wall_time,
               "max_displacement_mm": float(np.linalg.norm(solution.displacement, axis=1).max()),
               "notes": [str(w.message) for w in caught], "units": "mm, s"}
    write_text_atomically(out / "solution.json", json.dumps(summary, indent=1, allow_nan=True))
    print(f"{solution.status}: {solution.message}")
    print(f"  {solution.steps} steps in {solution.wall_time:.2f} s; max displacement {summary['max_displacement_mm']:.3f} mm")
    print(f"  written to {out}")
    return 0 if solution.ok else 1


def add_parsers(sub) -> None:
    """Register ``niftysim export`` and ``niftysim run`` on ``sub`` (argparse sub-parsers)."""
    p = sub.add_parser("niftysim", help="exchange models with NiftySim: export a case, run a NiftySim model here")
    inner = p.add_subparsers(dest="niftysim_command", required=True)
    e = inner.add_parser("export", help="write a case file as a NiftySim XML model (SI units)")
    e.add_argument("case", help="case file (.json, as `breastbiomech mesh` writes it)")
    e.add_argument("--out", required=True, help="the NiftySim model file to write (.xml)")
    e.add_argument("--solved", help="deformed.vtu of `breastbiomech simulate CASE`: write the plates and supports as the "
                                    "solved displacements of the nodes they hold (NiftySim's CPU build runs it)")
    e.add_argument("--formulation", choices=["T4ANP", "T4"], help="element formulation (default: the case's)")
    e.set_defaults(func=cmd_export)
    r = inner.add_parser("run", help="solve a NiftySim XML model as NiftySim would (physical time)")
    r.add_argument("model", help="NiftySim model (.xml)")
    r.add_argument("--out", required=True, help="output folder (new or empty)")
    r.add_argument("--device", type=device_argument, default=None, help="warp device (cpu, cuda, cuda:1; default: warp's)")
    r.add_argument("--quiet", action="store_true", help="no progress on standard error")
    r.set_defaults(func=cmd_run)
