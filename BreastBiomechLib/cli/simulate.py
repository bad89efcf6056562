"""``breastbiomech simulate``: solve a case file."""

from __future__ import annotations

import json
import sys
from dataclasses import replace

import numpy as np

from BreastBiomechLib.cli.common import device_argument
from BreastBiomechLib.cli.events import SILENT, add_progress_option, events_of, wants_bar
from BreastBiomechLib.io.cases import read_case
from BreastBiomechLib.io.solutions import write_solution
from BreastBiomechLib.solver.run_case import run_case


def cmd_simulate(args) -> int:
    """Solve CASE.json; write the mesh with its displacement and a JSON summary of the solve."""
    import warp as wp

    model, settings = read_case(args.case)
    settings = replace(settings, device=args.device or settings.device)
    mesh = model.mesh
    print(f"simulate {args.case}: {len(mesh.nodes)} nodes, {len(mesh.tets)} tets, {model.formulation}, "
          f"{settings.method}, device {settings.device or 'default'}")

    bar, events = wants_bar(args), events_of(args)
    device = wp.get_device(settings.device)
    what = ("dynamic relaxation" if settings.method == "relaxation" else f"{settings.method} solve") + \
        f" on {'the GPU (' + device.name + ')' if device.is_cuda else 'the CPU'}"

    def report(fraction):
        if bar:
            print(f"\r  {fraction:6.1%} of the step budget", end="", file=sys.stderr, flush=True)
        events.progress(f"{what}: {fraction:.0%} of the step budget", fraction)

    def unloaded_report(iteration, residual):
        message = f"unloaded shape: iteration {iteration}, largest node mismatch {residual:.4f} mm"
        if bar:
            print(f"  {message}", file=sys.stderr)
        events.progress(message)

    events.progress("estimating the unloaded (stress-free) shape" if settings.unloaded is not None
                    else f"{what}: starting", 0.0)
    quiet = not bar and events is SILENT
    result = run_case(model, settings, progress=None if quiet else report,
                      reference_progress=None if quiet else unloaded_report)
    solution, model, reference_state = result.solution, result.model, result.reference_state
    if reference_state is not None:
        print(f"  unloaded reference state: {reference_state['iterations']} iterations, residual "
              f"{reference_state['residual_mm']:.3g} mm, largest gravity sag {reference_state['largest_sag_mm']:.2f} mm, "
              f"{reference_state['wall_s']:.1f} s")
    if bar:
        print(file=sys.stderr)
    mesh_path, summary_path = write_solution(args.out, mesh, result)
    summary = json.loads(summary_path.read_text())
    events.output("device", device.alias)
    events.output("mesh", mesh_path)
    events.output("solution", summary_path)
    print(f"{solution.status}: {solution.message}")
    print(f"  {solution.steps} steps in {solution.wall_time:.2f} s; max displacement "
          f"{summary['max_displacement_mm']:.2f} mm")
    for name, force in summary["plates"].items():
        print(f"  plate {name}: force {np.linalg.norm(force):.3f} N (normal {summary['plate_normal_forces'][name]:.3f} N, "
              f"tangential {np.linalg.norm(summary['plate_tangential_forces'][name]):.3f} N)")
    for note in model.loading.notes:
        print(f"  support: {note}")
    print(f"  written: {mesh_path} (point array 'displacement', mm) and {summary_path}")
    return 0 if solution.ok else 1


def add_parsers(sub) -> None:
    """Register the ``simulate`` command on ``sub`` (argparse sub-parsers)."""
    p = sub.add_parser("simulate", help="solve a case file (mesh + materials + loading, see docs/solver.md)")
    p.add_argument("case", help="CASE.json")
    p.add_argument("--out", required=True, help="output folder for deformed.vtu and solution.json")
    p.add_argument("--device", type=device_argument, default=None, help="cuda, cpu or a warp device name (default: the case's, or warp's)")
    add_progress_option(p)
    p.set_defaults(func=cmd_simulate)
