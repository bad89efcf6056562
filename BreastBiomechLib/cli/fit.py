"""``breastbiomech optimise|study``: material fits of compressed cases, one case or the seed's
four-model study."""

from __future__ import annotations

import datetime
import json
import sys
import time
from pathlib import Path

from BreastBiomechLib.cli.common import (MODEL_CHOICES, OBJECTIVE_CHOICES, add_cluster_options, cohort_progress,
                                         device_argument, end_progress, finite, non_negative_int, positive,
                                         positive_int, report_failures)
from BreastBiomechLib.cli.events import add_progress_option, events_of, wants_bar
from BreastBiomechLib.cohort import place


def cmd_optimise(args) -> int:
    """Fit material parameters to a compressed case (seed section 2.4)."""
    from BreastBiomechLib.io.case_layout import CaseLayout
    from BreastBiomechLib.optimisation.case import FitSettings, fit_compressed_case

    settings = FitSettings(model=args.model, free=tuple(args.free), fibre=tuple(args.fibre), edge_mm=args.edge_mm,
                           optimiser=args.optimiser, budget=args.budget, seconds=args.seconds, seed=args.seed,
                           objective=args.objective, bins=args.bins, tolerance_mm=args.tolerance_mm,
                           population=args.population)
    started = time.perf_counter()
    bar, events = wants_bar(args), events_of(args)

    def progress(done, budget, best, phase):
        if bar:
            width = 30
            filled = int(width * done / budget)
            print(f"\r  [{'#' * filled}{'.' * (width - filled)}] {done}/{budget} {phase:6s} best {best:.5f} "
                  f"{time.perf_counter() - started:6.0f} s", end="", file=sys.stderr, flush=True)
        events.progress(f"{done}/{budget} forward solves ({phase}), best objective {best:.5f}", done / budget)

    events.progress(f"{settings.model} fit: preparing the case and the fitting mesh", 0.0)
    layout = CaseLayout(args.case_dir)
    if args.states is not None:
        unused = layout.unused_states_note(args.states, why="--states chose them")
        if unused:
            print(f"breastbiomech optimise: note: {unused}", file=sys.stderr)
            events.progress(unused, 0.0)
    fit = fit_compressed_case(args.case_dir, args.out, settings, labels=args.labels, mesh_path=args.mesh,
                              resume=args.resume, device=args.device, progress=progress, states=args.states)
    events.output("fit", fit.folder)
    if bar:
        print(file=sys.stderr)
    summary = fit.result.summary()
    if args.json:
        print(json.dumps({**summary, "landmark_errors": fit.landmark_errors, "force_scale": fit.force_scale}))
        return 0
    best = fit.result.best
    print(f"{settings.model} fit of {args.case_dir} ({settings.optimiser}, {summary['evaluations']} evaluations, "
          f"{summary['replayed']} replayed, stopped: {summary['stopped']}, {summary['seconds']:.0f} s)")
    print(f"  best objective {best.objective:.5f}: NMI {best.nmi:.4f}, NCC {best.ncc:.4f}")
    from BreastBiomechLib.optimisation.run import SETTLED

    gain = fit.result.recent_gain()
    if not gain <= SETTLED:
        print(f"  not settled: the best objective still fell by {gain:.4f} over the last half of the solves; "
              "raise --budget (--resume goes on from these)")
    for name, values in fit.result.materials.items():
        print(f"  {name:10s} E {values['E']:10.0f} Pa  nu {values['nu']:.4f}  eta {values['eta']:10.1f} Pa")
    if "fibre" in fit.result.geometry:
        print("  fibre direction (LPS) " + " ".join(f"{v:.3f}" for v in fit.result.geometry["fibre"]))
    if "plate_offsets_mm" in fit.result.geometry:
        print("  plate offsets (mm, towards the tissue) " + " ".join(f"{v:.2f}" for v in fit.result.geometry["plate_offsets_mm"]))
    for name, figures in best.states.items():
        print(f"  state {name}: objective {figures['objective']:.5f}, NMI {figures['nmi']:.4f}"
              + (f", landmark error {figures['landmark_mean_mm']:.2f} mm (mean)"
                 if figures["landmark_mean_mm"] == figures["landmark_mean_mm"] else ""))
    if fit.force_scale is not None:
        f = fit.force_scale
        if f["scale"] is None:
            print(f"  measured plate force not used: {f['reason']}")
        else:
            fat = f["materials"].get("fat", {}).get("E")
            print(f"  absolute moduli from the measured plate force{'s' if len(f['states']) > 1 else ''}: the fitted "
                  f"moduli x {f['scale']:.3f} (sd {f['sd']:.3f})" + (f", fat E {fat:.0f} Pa" if fat else "")
                  + " (force_scale.json)")
    if fit.landmark_errors:
        e = fit.landmark_errors
        print(f"  landmarks{' (first state)' if best.states else ''}: displacement {e['displacement_mm']['mean']:.2f} ± {e['displacement_mm']['sd']:.2f} mm, "
              f"error {e['error_mm']['mean']:.2f} ± {e['error_mm']['sd']:.2f} mm (max {e['error_mm']['max']:.2f})")
    print(f"  results in {fit.folder}")
    return 0


def cmd_study(args) -> int:
    """The four-model study of the seed's Tables 2 and 3 on compressed cases."""
    from BreastBiomechLib.optimisation.study import StudySettings, provenance, run_study, study_markdown, write_report
    from BreastBiomechLib.phantom.compressed_files import compressed_folder

    budgets = {}
    for item in args.budget or []:
        model, _, count = item.partition("=")
        if model not in MODEL_CHOICES or not count.isdigit():
            raise ValueError(f"--budget takes MODEL=SOLVES with MODEL one of {MODEL_CHOICES}, not {item!r}")
        budgets[model] = int(count)
    settings = StudySettings(models=tuple(args.models), optimisers=tuple(args.optimisers),
                             budgets={**StudySettings().budgets, **budgets}, fibre=tuple(args.fibre),
                             edge_mm=args.edge_mm, seed=args.seed, bins=args.bins, tolerance_mm=args.tolerance_mm)
    for case_dir in args.case_dirs:  # every case is there before a cluster starts
        compressed_folder(case_dir)
    placement = place(args.scheduler, args.workers, args.device)
    run = run_study(args.case_dirs, args.out, settings, placement=placement, progress=cohort_progress(args.quiet))
    end_progress()
    rows = run.rows
    if args.report:
        import warp as wp

        wp.init()
        device = wp.get_device(args.device) if args.device else wp.get_device()
        info = provenance(f"{device.name} ({device.alias})", "breastbiomech " + " ".join(args.argv),
                          datetime.date.today().isoformat())
        write_report(args.report, study_markdown(rows, settings, info))
        print(f"tables written to {args.report}")
    for row in sorted(rows, key=lambda r: (r.case, r.model, r.optimiser)):
        s = row.landmark_errors["error_mm"] if row.landmark_errors else None
        print(f"{row.case:8s} {row.model:13s} {row.optimiser:7s} NMI {row.nmi:.4f} "
              + (f"landmark error {s['mean']:.2f} ± {s['sd']:.2f} mm (max {s['max']:.1f})" if s else "")
              + f" {row.evaluations} solves, {row.stopped}")
    report_failures(run.failed, Path(args.out) / "failures.log")
    return 1 if run.failed else 0


def add_parsers(sub) -> None:
    """Register the ``optimise``, ``study`` commands on ``sub`` (argparse sub-parsers)."""
    p = sub.add_parser("optimise", help="fit tissue material parameters to a compressed case by maximising NMI")
    p.add_argument("case_dir", help="a case folder with its compressed/ part (`breastbiomech phantom --compressed`)")
    p.add_argument("--out", required=True, help="output folder (results written as the fit goes)")
    p.add_argument("--model", choices=MODEL_CHOICES, default="aniso-hetero", help="the seed's model variant")
    p.add_argument("--free", nargs="+", choices=("E", "nu", "eta", "fibre", "offset"), default=["E", "nu", "eta"],
                   help="parameters searched per material (fat's E is the reference, eta only for aniso models); "
                        "fibre: the fibre direction's angles (aniso models); offset: each plate's position")
    p.add_argument("--fibre", type=finite, nargs=3, default=[0.0, 0.0, 1.0], metavar=("X", "Y", "Z"),
                   help="fibre direction of the anisotropic models (LPS unit vector; default SI)")
    p.add_argument("--optimiser", choices=("hybrid", "cmaes", "cmaes-local"), default="hybrid",
                   help="hybrid: annealing then L-BFGS-B (the seed's); cmaes: CMA-ES, one batch per generation; "
                        "cmaes-local: CMA-ES on 60 %% of the budget, then L-BFGS-B (for budgets of tens of solves)")
    p.add_argument("--budget", type=positive_int, default=500, help="forward solves in all (default 500)")
    p.add_argument("--seconds", type=positive, help="wall-time limit of this run (s)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="random seed (same seed, same run)")
    p.add_argument("--population", type=positive_int, help="CMA-ES population per generation (default 4 + 3 ln d)")
    p.add_argument("--objective", choices=OBJECTIVE_CHOICES, default="nmi",
                   help="nmi (the seed's), landmarks (mean error), surface (mean distance of the predicted breast "
                        "skin to the measured body surface) or a weighted sum with NMI (default nmi)")
    p.add_argument("--bins", type=positive_int, default=64, help="NMI histogram bins (default 64)")
    p.add_argument("--mesh", help="fitting mesh (.vtu from `breastbiomech mesh` of a segmentation); default: the "
                                  "case's MR segmented from its seed points (seeds_muscle/seeds_tumour.mrk.json), "
                                  "meshed at --edge-mm")
    p.add_argument("--labels", help="a segmentation's label map, meshed at --edge-mm, instead (a phantom case's own "
                                    "labels.nrrd is its ground truth: name it only on purpose)")
    p.add_argument("--edge-mm", type=positive, default=4.0, help="fitting mesh element size (default 4 mm)")
    p.add_argument("--tolerance-mm", type=positive, default=0.01, help="forward solves' relaxation tolerance (mm)")
    p.add_argument("--device", type=device_argument, help="warp device (cuda, cpu; default: warp's)")
    p.add_argument("--states", nargs="+", metavar="NAME",
                   help="the measured states fitted (compressed, and names under the case's states/); default: every "
                        "state of the case, jointly (one set of materials, each state its own plates)")
    p.add_argument("--resume", action="store_true", help="continue a fit interrupted in --out")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    add_progress_option(p)
    p.set_defaults(func=cmd_optimise)

    p = sub.add_parser("study", help="the four model variants fitted to compressed cases (the seed's Tables 2, 3)")
    p.add_argument("case_dirs", nargs="+", help="compressed case folders (`make table1-cases`: out/table1/case*)")
    p.add_argument("--out", required=True, help="results folder (rerun to resume)")
    p.add_argument("--models", nargs="+", choices=MODEL_CHOICES, default=list(MODEL_CHOICES))
    p.add_argument("--optimisers", nargs="+", choices=("hybrid", "cmaes", "cmaes-local"), default=["cmaes"])
    p.add_argument("--budget", nargs="+", metavar="MODEL=SOLVES",
                   help="forward solves per fit of a model (default iso-homo=24 aniso-homo=48 iso-hetero=160 "
                        "aniso-hetero=240)")
    p.add_argument("--fibre", type=finite, nargs=3, default=[0.0, 0.0, 1.0], metavar=("X", "Y", "Z"),
                   help="fibre direction of the anisotropic models (LPS unit vector; default SI)")
    p.add_argument("--edge-mm", type=positive, default=4.0, help="fitting mesh element size (default 4 mm)")
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument("--bins", type=positive_int, default=64, help="NMI histogram bins (default 64)")
    p.add_argument("--tolerance-mm", type=positive, default=0.01, help="forward solves' relaxation tolerance (mm)")
    p.add_argument("--device", type=device_argument, help="warp device: cuda (every GPU), cuda:K (GPU K), cpu; default: the GPUs if any")
    add_cluster_options(p)
    p.add_argument("--report", help="Markdown file whose study tables are (re)written, e.g. docs/validation.md")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_study)
