"""``breastbiomech diagnose``: name the physical effect a fitted model is missing, add it, refit,
and report the gap before and after (:mod:`BreastBiomechLib.discrepancy`)."""

from __future__ import annotations

import json
import sys

from BreastBiomechLib.cli.common import (device_argument, fraction, non_negative, non_negative_int, positive,
                                         positive_int)
from BreastBiomechLib.cli.events import add_progress_option, events_of, wants_bar
from BreastBiomechLib.discrepancy.acquisitions import KINDS
from BreastBiomechLib.discrepancy.effects import NAMES
from BreastBiomechLib.discrepancy.observations import CHANNELS, FLOORS


def cmd_diagnose(args) -> int:
    from BreastBiomechLib.discrepancy import DiagnosisSettings, run_diagnosis
    from BreastBiomechLib.discrepancy.registration import RegistrationSettings
    from BreastBiomechLib.io.case_layout import CaseLayout
    from BreastBiomechLib.optimisation.case import recorded_states

    noise = _noise(args)
    settings = DiagnosisSettings(alpha=args.alpha, refine_iterations=args.refine_iterations,
                                 profile=args.interval == "profile")

    bar, events = wants_bar(args), events_of(args)

    def progress(message):
        if bar:
            print(f"  {message}", file=sys.stderr, flush=True)
        events.progress(message)

    unused = CaseLayout(args.case_dir).unused_states_note(
        recorded_states(args.fit), why="the fit did not use them; fit them jointly (`breastbiomech optimise`) to "
                                       "diagnose them")
    if unused:
        print(f"breastbiomech diagnose: note: {unused}", file=sys.stderr)
        events.progress(unused)
    run = run_diagnosis(args.case_dir, args.fit, args.out, effects=args.effects, rounds=args.rounds, noise=noise,
                        settings=settings, device=args.device, resume=args.resume, progress=progress,
                        registration=None if args.no_residual_field else RegistrationSettings(),
                        one_round=args.one_round, add=args.add,
                        design=None if args.design is None else tuple(args.design))
    events.output("diagnosis", run.folder)
    if args.json:
        summary = {"final": run.final["verdict"], "sentence": run.final["sentence"], "added": run.added,
                   "rounds": len(run.rounds)}
        if args.design is not None:
            summary["design"] = _design_summary(run.folder)
        print(json.dumps(summary))
        return 0
    for record in run.rounds:
        d = record["diagnosis"]
        print(f"round {record['round']}: {d['sentence']}")
        before = record["before"].get("landmark_error_mm")
        after = (record.get("after") or {}).get("landmark_error_mm")
        if before and after:
            print(f"  landmark error {before['mean']:.2f} -> {after['mean']:.2f} mm (mean); NMI "
                  f"{record['before']['nmi']:.4f} -> {record['after']['nmi']:.4f}")
    if args.design is not None:
        _print_design(run.folder)
    print(f"report: {run.folder / 'report.md'}; every statistic: {run.folder / 'diagnosis.json'}")
    return 0


def _design_summary(folder) -> dict:
    """``designed_for`` and the sentences of ``folder``'s design.json (:meth:`DiagnosisSession.design`)."""
    from BreastBiomechLib.discrepancy.design_record import DESIGN_FILE, design_sentences

    record = json.loads((folder / DESIGN_FILE).read_text())
    return {"undecided": record.get("undecided", []), "designed_for": record["designed_for"],
            "sentences": design_sentences(record)}


def _print_design(folder) -> None:
    for sentence in _design_summary(folder)["sentences"]:
        print(f"next measurement: {sentence}")


def cmd_design(args) -> int:
    from pathlib import Path

    from BreastBiomechLib.discrepancy.design import design, last_round_state
    from BreastBiomechLib.discrepancy.fitted import load_fitted_case
    from BreastBiomechLib.io.atomic import write_json_atomically, write_text_atomically

    out = Path(args.out)
    if out.exists() and any(out.iterdir()):
        raise ValueError(f"{out} exists and is not empty: choose a new output folder")
    noise = _noise(args)
    bar, events = wants_bar(args), events_of(args)

    def progress(message):
        if bar:
            print(f"  {message}", file=sys.stderr, flush=True)
        events.progress(message)

    fitted = load_fitted_case(args.case_dir, args.fit, device=args.device)
    state = None
    if args.diagnosis is not None:  # from the model its last round ended with (its added effects, refitted)
        state = last_round_state(fitted, args.diagnosis)
    made = design(fitted, effects=args.effects, kinds=tuple(args.acquisitions), noise=noise, alpha=args.alpha,
                  state=state, progress=progress)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomically(out / "design.json", made.to_dict())
    write_text_atomically(out / "design.md", made.markdown())
    events.output("design", out)
    if args.json:
        print(json.dumps(made.to_dict()))
        return 0
    for sentence in made.sentences():
        print(sentence)
    print(f"report: {out / 'design.md'}; every separation: {out / 'design.json'}")
    return 0


def _add_noise_options(p, measured_floor: bool) -> None:
    """The noise model's and the test level's options (:func:`_noise`); ``measured_floor``: a
    ``--floor`` choice (else the floor is the fixed one)."""
    p.add_argument("--channels", nargs="+", choices=CHANNELS, default=list(CHANNELS),
                   help="what is compared (default: landmarks and the body surface)")
    p.add_argument("--landmark-sd-mm", type=non_negative, default=0.5,
                   help="landmark localisation error per coordinate (mm, default 0.5)")
    if measured_floor:
        p.add_argument("--floor", choices=FLOORS, default="measured",
                       help="the model-error floor added to every feature's noise: measured from the case (the "
                            "fitted model solved again on its refined fitting mesh: one solve of 8x the tets) or "
                            "fixed at --model-sd-mm (default measured)")
    p.add_argument("--model-sd-mm", type=non_negative, default=0.5,
                   help="the model-error floor (mm, default 0.5): the measured floor's lower bound, or with "
                        "--floor fixed the floor itself" if measured_floor else
                        "the model-error floor added to every feature (mm, default 0.5; a measured floor is not "
                        "simulated)")
    p.add_argument("--surface-spacing-mm", type=positive, default=8.0,
                   help="one surface feature per cube of this size (mm, default 8)")
    p.add_argument("--alpha", type=fraction, default=0.01, help="family-wise significance level (default 0.01)")


def _noise(args):
    """The :class:`~BreastBiomechLib.discrepancy.NoiseModel` of :func:`_add_noise_options`' options."""
    from BreastBiomechLib.discrepancy import NoiseModel

    return NoiseModel(landmark_sd_mm=args.landmark_sd_mm, model_sd_mm=args.model_sd_mm,
                      surface_spacing_mm=args.surface_spacing_mm, channels=tuple(args.channels),
                      floor=getattr(args, "floor", "fixed"))


def add_parsers(sub) -> None:
    """Register the ``diagnose`` command on ``sub`` (argparse sub-parsers)."""
    p = sub.add_parser("diagnose", help="name the effect a fitted model is missing, add it, refit, report")
    p.add_argument("case_dir", help="the compressed case folder the fit was made on")
    p.add_argument("--fit", required=True, help="the fit's folder (`breastbiomech optimise --out`)")
    p.add_argument("--out", required=True, help="a new output folder (or an interrupted run's, with --resume)")
    p.add_argument("--effects", nargs="+", choices=NAMES, help="candidate effects (default: the whole library)")
    p.add_argument("--rounds", type=positive_int, default=3, help="rounds of diagnose, add and refit at most (default 3)")
    _add_noise_options(p, measured_floor=True)
    p.add_argument("--refine-iterations", type=non_negative_int, default=2,
                   help="Gauss-Newton iterations refining the refit of an added effect (default 2)")
    p.add_argument("--interval", choices=("profile", "linearised"), default="profile",
                   help="the added effect's 95 %% intervals: profile likelihood (up to 3 solves per side of each "
                        "parameter; right where an effect saturates, as friction above sticking) or linearised from "
                        "the refit's sensitivities (no solve; default profile)")
    p.add_argument("--no-residual-field", action="store_true",
                   help="skip the residual displacement field (the deformable registration of the predicted to the "
                        "measured image, its maps and pictures; about 10-60 s per round)")
    p.add_argument("--device", type=device_argument, help="warp device (cuda, cpu; default: warp's)")
    p.add_argument("--resume", action="store_true", help="continue an interrupted run in --out")
    p.add_argument("--one-round", action="store_true",
                   help="diagnose the next round (an open one again) and stop before adding anything: the round "
                        "waits for a decision (--add), its diagnosis kept in --out")
    p.add_argument("--add", choices=NAMES, metavar="EFFECT",
                   help="with --resume: add EFFECT (one the open last round tested) to the model, refit, and stop")
    p.add_argument("--design", nargs="*", metavar="KIND_OR_NAME",
                   help="once the rounds are done, design the next measurement for the candidates the last round "
                        "could not tell apart: each acquisition of these kinds (" + ", ".join(KINDS) + ") or names "
                        "(none given: all) simulated from the model, design.md and a report section (a few solves "
                        "per acquisition: seconds on a GPU, one to two minutes on 2 CPU cores)")
    p.add_argument("--json", action="store_true", help="print the final verdict as one JSON line")
    add_progress_option(p)
    p.set_defaults(func=cmd_diagnose)

    p = sub.add_parser("design", help="which further acquisition would tell each candidate effect apart from what "
                                      "takes it up at this fit")
    p.add_argument("case_dir", help="the compressed case folder the fit was made on")
    p.add_argument("--fit", required=True, help="the fit's folder (`breastbiomech optimise --out`)")
    p.add_argument("--out", required=True, help="a new output folder (design.json, design.md)")
    p.add_argument("--effects", nargs="+", choices=NAMES, help="candidate effects (default: the whole library)")
    p.add_argument("--diagnosis", help="a diagnosis folder of this fit (`breastbiomech diagnose --out`): design from "
                                       "the model its last round ended with (the effects it added, refitted)")
    p.add_argument("--acquisitions", nargs="+", default=list(KINDS), metavar="KIND_OR_NAME",
                   help=f"further acquisitions simulated, by kind ({', '.join(KINDS)}; default: all) or name (e.g. "
                        "only-left): the closure 10 and 20 %% of the thickness further or less, all of it by one "
                        "plate, the plates turned 90 degrees")
    _add_noise_options(p, measured_floor=False)
    p.add_argument("--device", type=device_argument, help="warp device (cuda, cpu; default: warp's)")
    p.add_argument("--json", action="store_true", help="print the design as one JSON line")
    add_progress_option(p)
    p.set_defaults(func=cmd_design)
