"""``breastbiomech discrepancy-suite``: the hidden-effect suite that proves the discrepancy
workflow (:mod:`BreastBiomechLib.discrepancy.suite`), resumable, its cases as cohort tasks on Dask."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

from BreastBiomechLib.cli.common import (add_cluster_options, cohort_progress, device_argument, fraction, non_negative,
                                         non_negative_int, positive, positive_int, report_failures)
from BreastBiomechLib.cohort import place
from BreastBiomechLib.discrepancy.suite import (ANATOMIES, SuiteSettings, run_suite, scores_markdown, suite_cases,
                                                suite_scores)
from BreastBiomechLib.discrepancy.suite.varied import VARIED_ANATOMIES, varied_cases
from BreastBiomechLib.io.atomic import write_text_atomically


def cmd_suite(args) -> int:
    out = Path(args.out)
    if args.varied:
        cases = varied_cases(args.varied, args.varied_seed, args.anatomies or VARIED_ANATOMIES, args.hidden)
        if args.two_state:
            cases = [replace(c, states=2) for c in cases]
    else:
        cases = suite_cases(args.anatomies or ANATOMIES, args.hidden, states=2 if args.two_state else 1)
    settings = SuiteSettings(compression=args.compression,
                             spacing_mm=None if args.spacing is None else tuple(args.spacing),
                             truth_edge_mm=args.truth_edge_mm, fit_edge_mm=args.fit_edge_mm,
                             fit_surface_edge_mm=args.fit_surface_edge_mm,
                             refine_interfaces=not args.no_refine, fit_blur_mm=args.fit_blur_mm, fit_budget=args.fit_budget,
                             fit_population=args.fit_population, rounds=args.rounds,
                             landmark_noise_mm=args.landmark_noise_mm, chest_clearance_mm=args.chest_clearance_mm,
                             moving_plate=args.moving_plate)
    if args.score_only:
        if not (out / "settings.json").is_file():
            raise FileNotFoundError(f"{out}: no suite run to score (no settings.json); run "
                                    "`breastbiomech discrepancy-suite --out DIR` first, or give its folder")
    else:
        placement = place(args.scheduler, args.workers, args.device)
        failed = [o for o in run_suite(out, cases, settings, placement, progress=cohort_progress(args.quiet))
                  if not o.ok]
        report_failures(failed, out / "failures.log")
    results = [json.loads((out / c.name / "result.json").read_text()) if (out / c.name / "result.json").is_file()
               else json.loads((out / c.name / "error.json").read_text()) if (out / c.name / "error.json").is_file()
               else None for c in cases]
    finished = [r for r in results if r is not None]
    scores = suite_scores(finished)
    write_text_atomically(out / "scores.json", json.dumps(scores, indent=1) + "\n")
    write_text_atomically(out / "scores.md", scores_markdown(scores, finished))
    if args.json:
        print(json.dumps({k: scores[k] for k in ("cases", "finished", "right_verdicts", "false_alarms",
                                                  "false_unexplained_after_right", "truth_in_interval",
                                                  "friction_within_0.2", "mean_rounds", "landmark_error_fall",
                                                  "nmi_gap_closed", "seconds_per_case")}))
    else:
        print(f"{len(finished)} of {len(cases)} cases done; scores: {out / 'scores.md'}")
    return 0


def add_parsers(sub) -> None:
    """Register the ``discrepancy-suite`` command on ``sub`` (argparse sub-parsers)."""
    from BreastBiomechLib.discrepancy.suite import HIDDEN_EFFECTS, SuiteSettings
    from BreastBiomechLib.discrepancy.suite.cases import BY_REQUEST, DEFAULT_HIDDEN

    d = SuiteSettings()
    p = sub.add_parser("discrepancy-suite", help="hidden-effect suite: make, fit and diagnose phantom cases "
                                                 "hiding known, unknown or no effects; score the verdicts")
    p.add_argument("--out", required=True, help="suite folder (a run resumes in it)")
    p.add_argument("--anatomies", nargs="+", type=int, choices=VARIED_ANATOMIES,
                   help="anatomies: the Table 1 presets 1-5 (default all five); with --varied also the sweep "
                        "variants 6-11 (default all eleven)")
    p.add_argument("--hidden", nargs="+", choices=list(HIDDEN_EFFECTS),
                   help="hidden effects (default all but " + ", ".join(BY_REQUEST) + ": "
                        + ", ".join(DEFAULT_HIDDEN) + ")")
    p.add_argument("--varied", type=positive_int, metavar="N",
                   help="the varied suite's first N cases instead: each draws its anatomy, compression, rig, "
                        "landmark noise, fit budget, fitting and truth mesh sizes and its effect's size (a third "
                        "null cases); the options below are then the run's defaults, which the draws replace")
    p.add_argument("--two-state", action="store_true",
                   help="each case also with a second scan: the one the design step recommends after the one-scan "
                        "diagnosis, made from the truth, then both scans fitted and diagnosed jointly (issue 78)")
    p.add_argument("--varied-seed", type=non_negative_int, default=0, help="the varied suite's draws (default 0)")
    p.add_argument("--compression", type=fraction, default=d.compression,
                   help=f"fraction of the breast thickness the plates close (default {d.compression})")
    p.add_argument("--spacing", type=positive, nargs=3, metavar=("L", "P", "S"),
                   help="phantom voxel size in mm (default: the presets' 1 x 1 x 2.5)")
    p.add_argument("--truth-edge-mm", type=positive, default=d.truth_edge_mm,
                   help=f"truth mesh element size (default {d.truth_edge_mm:g} mm)")
    p.add_argument("--fit-edge-mm", type=positive, default=d.fit_edge_mm,
                   help=f"fitting mesh element size (default {d.fit_edge_mm:g} mm)")
    p.add_argument("--fit-surface-edge-mm", type=positive, default=d.fit_surface_edge_mm,
                   help=f"fitting mesh's skin triangles (default {d.fit_surface_edge_mm:g} mm)")
    p.add_argument("--fit-blur-mm", type=non_negative, default=d.fit_blur_mm,
                   help=f"smoothing of the segmentation's surface before the fitting mesh (default {d.fit_blur_mm:g} mm)")
    p.add_argument("--no-refine", action="store_true", help="fitting meshes without interface refinement")
    p.add_argument("--fit-budget", type=positive_int, default=d.fit_budget,
                   help=f"forward solves of each material fit (default {d.fit_budget})")
    p.add_argument("--fit-population", type=positive_int, default=d.fit_population,
                   help=f"CMA-ES population (default {d.fit_population})")
    p.add_argument("--chest-clearance-mm", type=non_negative,
                   help="how far anterior to the chest the plates' flat faces end (mm; default: the plate travel)")
    p.add_argument("--moving-plate", choices=("both", "first", "second"), default=d.moving_plate,
                   help=f"which plate closes on the breast (default {d.moving_plate}: half the travel each; second: "
                        "the lateral one towards the held medial one, the seed's rig)")
    p.add_argument("--rounds", type=positive_int, default=d.rounds, help=f"diagnosis rounds at most (default {d.rounds})")
    p.add_argument("--landmark-noise-mm", type=non_negative, default=d.landmark_noise_mm,
                   help="localisation error (sd per coordinate, mm) put on the measured landmarks of each image "
                        f"(default {d.landmark_noise_mm:g})")
    p.add_argument("--device", type=device_argument, help="warp device: cuda (every GPU), cuda:K (GPU K), cpu; default: the GPUs if any")
    add_cluster_options(p)
    p.add_argument("--score-only", action="store_true", help="score the finished cases, run nothing")
    p.add_argument("--json", action="store_true", help="print the headline scores as one JSON line")
    p.add_argument("--quiet", action="store_true", help="no progress on standard error")
    p.set_defaults(func=cmd_suite)
