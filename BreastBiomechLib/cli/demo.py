"""``breastbiomech demo``: the main job on the built-in phantom, with its Markdown report."""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from BreastBiomechLib import __version__
from BreastBiomechLib.cli.common import device_argument, positive, positive_int
from BreastBiomechLib.io.atomic import write_text_atomically
from BreastBiomechLib.timing import StageClock, clocked, stage


def clear_earlier_result(folder: Path, marker: str = "settings.json", what: str = "fit") -> None:
    """Remove the fit (or, with ``marker`` "diagnosis.json", the diagnosis) an earlier demo run
    left in ``folder``: the demo remakes its phantom, segmentation and mesh on every run, so that
    result is stale (resuming it would replay evaluations of another mesh). A folder that holds
    no such result (no ``marker`` file) is refused."""
    if not folder.exists():
        return
    if not (folder / marker).is_file():
        raise FileExistsError(f"{folder} exists and holds no earlier demo {what}; choose another --out for the demo")
    print(f"    replacing the earlier run's {what} in {folder}")
    shutil.rmtree(folder)


def cmd_demo(args) -> int:
    """The main job on the built-in phantom: phantom and its compressed "measured" scan,
    segmentation from seed points, FE mesh of the segmentation, a simulation with the starting
    materials, the material fit, and a Markdown report (out/demo/report.md)."""
    run_demo(Path(args.out), args.device, args.budget, args.truth_edge_mm, args.fit_edge_mm)
    return 0


@dataclass(frozen=True)
class DemoMeshes:
    """The demo's meshes (element sizes in mm) and the fit's forward solves, by device: on a
    GPU a 2 mm truth mesh and a 4 mm fitting mesh with a 2 mm skin and refined tissue interfaces
    (about 230k tets), 200 solves of CMA-ES; on a CPU coarser voxels (1.5 x 1.5 x 3 mm), a 6 mm
    truth mesh and a 5 mm fitting mesh of a smoother surface (3 mm blur), its skin as coarse as
    its inside and no interface refinement (tissues by voxel majority; about 27k tets), 19 solves
    (two generations of five, then three batched gradients). The CPU mesh's elements stay 5 mm
    deep inside, where the pectoral muscle is: an 8 mm mesh with a 4 mm skin (45k tets, its
    inside 8 mm) fitted the muscle 45-60 % stiffer than the GPU's 4 mm mesh of the same case
    (docs/journal/2026-12-06-demo-fitting-mesh-and-stage-times.md)."""

    truth_edge_mm: float
    fit_edge_mm: float
    fit_skin_mm: float
    refine_interfaces: bool
    blur_mm: float
    spacing_mm: tuple[float, float, float]
    budget: int

    @classmethod
    def for_device(cls, gpu: bool, truth_edge_mm: float | None = None, fit_edge_mm: float | None = None,
                   budget: int | None = None) -> "DemoMeshes":
        """The device's defaults, with any of ``truth_edge_mm``, ``fit_edge_mm`` (its skin at the
        device's ratio: half of it on a GPU, all of it on a CPU) and ``budget`` given instead."""
        for name, value in (("truth_edge_mm", truth_edge_mm), ("fit_edge_mm", fit_edge_mm), ("budget", budget)):
            if value is not None and not value > 0:
                raise ValueError(f"the demo's {name} must be positive, not {value}")
        fit = fit_edge_mm or (4.0 if gpu else 5.0)
        return cls(truth_edge_mm or (2.0 if gpu else 6.0), fit, fit / 2 if gpu else fit, gpu, 0.8 if gpu else 3.0,
                   (1.0, 1.0, 2.5) if gpu else (1.5, 1.5, 3.0), budget or (200 if gpu else 19))


def run_demo(out: Path, device: str | None = None, budget: int | None = None, truth_edge_mm: float | None = None,
             fit_edge_mm: float | None = None) -> StageClock:
    """:func:`cmd_demo`'s work in ``out`` on ``device`` (default the GPU when there is one) with
    ``budget`` forward solves for the fit and the meshes of ``truth_edge_mm`` and ``fit_edge_mm``
    (each default the device's: :class:`DemoMeshes`); returns the wall seconds per stage
    (:mod:`~BreastBiomechLib.timing`; also written to out/stages.json and the report)."""
    with clocked() as clock:
        with stage("imports"):
            import warp as wp

            wp.init()
        gpu = (device or ("cuda" if wp.get_cuda_device_count() else "cpu")).startswith("cuda")
        if gpu:  # each stage holds its own kernels' time
            clock.synchronise = wp.synchronize
        meshes = DemoMeshes.for_device(gpu, truth_edge_mm, fit_edge_mm, budget)
        _demo(out, device, meshes, gpu, clock)
    write_text_atomically(out / "stages.json", json.dumps({**clock.to_dict(), "meshes": asdict(meshes)}, indent=2))
    return clock


def _demo(out: Path, device: str | None, meshes: DemoMeshes, gpu: bool, clock: StageClock) -> None:
    with stage("imports"):
        from BreastBiomechLib.discrepancy import DiagnosisSettings, NoiseModel, run_diagnosis
        from BreastBiomechLib.io.images import read_image
        from BreastBiomechLib.io.meshes import write_vtu
        from BreastBiomechLib.io.segmentation import write_segmentation
        from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels
        from BreastBiomechLib.optimisation.case import FitSettings, fit_compressed_case
        from BreastBiomechLib.phantom import generate_phantom, table1_case, write_phantom
        from BreastBiomechLib.phantom.compressed import compress_phantom, table1_truth
        from BreastBiomechLib.phantom.compressed_files import write_compressed
        from BreastBiomechLib.phantom.files import SEED_COUNTS
        from BreastBiomechLib.phantom.seeds import seed_points
        from BreastBiomechLib.segmentation import dice_per_tissue, segment_tissues
        from BreastBiomechLib.visualisation import save_overview

    truth_mm, fit_mm, skin_mm = meshes.truth_edge_mm, meshes.fit_edge_mm, meshes.fit_skin_mm
    spacing, budget = meshes.spacing_mm, meshes.budget
    report = {"steps": []}
    started = time.perf_counter()

    def step(text):
        report["steps"].append([text, time.perf_counter()])
        print(text, flush=True)

    print(f"BreastBiomech {__version__} demo -> {out} ({'GPU' if gpu else 'CPU'}: {truth_mm:g} mm truth mesh, "
          f"{fit_mm:g} mm fitting mesh, {budget} forward solves)")
    step(f"1/7 phantom: Table 1 case {DEMO_CASE} preset, {' x '.join(f'{v:g}' for v in spacing)} mm voxels, "
         "SNR 30, +-20 % bias")
    params = table1_case(DEMO_CASE)
    params.spacing_mm = spacing
    case = generate_phantom(params)
    paths = write_phantom(case, out / "case")
    s = case.summary
    print(f"    {s['breast_volume_cm3']:.0f} cm3, density {s['glandular_density']:.1%}; {s['seconds']:.1f} s")

    truth = table1_truth(DEMO_CASE)
    truth.edge_mm, truth.compression, truth.friction = truth_mm, DEMO_COMPRESSION, DEMO_FRICTION
    step(f"2/7 compressed 'measured' scan: truth simulation of {truth.compression:.0%} LR plate compression "
         f"on a {truth_mm:g} mm truth mesh, with plate friction mu {truth.friction:g} hidden in it (the fit's model "
         "has none), imaged with its own noise and bias")
    compressed = compress_phantom(case, truth, device=device)
    compressed_paths = write_compressed(compressed, out / "case")
    c = compressed.summary
    print(f"    {c['truth_tets']} tets, {c['solve_message']}; largest displacement {c['max_displacement_mm']:.1f} mm")

    step("3/7 segmentation from seed points (EM + MRF + bias field)")
    tumour = case.summary["tissue_volumes_cm3"].get("tumour", 0.0) > 0
    result = segment_tissues(case.image, seed_points(case.labels, "muscle", SEED_COUNTS["muscle"]).positions,
                             seed_points(case.labels, "tumour", SEED_COUNTS["tumour"]).positions if tumour else None)
    dice = dice_per_tissue(result.labels, case.labels)
    seg_paths = write_segmentation(result, out / "segmentation", {"dice_vs_truth": dice})
    print("    Dice vs the ground truth: " + ", ".join(f"{k} {v:.3f}" for k, v in dice.items()))

    step(f"4/7 tetrahedral fitting mesh of the segmentation ({fit_mm:g} mm, skin {skin_mm:g} mm"
         + (")" if meshes.refine_interfaces else ", tissues by voxel majority)"))
    mesh = mesh_labels(result.labels, MeshSettings(edge_mm=fit_mm, surface_edge_mm=skin_mm,
                                                   refine_interfaces=meshes.refine_interfaces, blur_mm=meshes.blur_mm),
                       nipple_mm=case.landmarks.position("nipple"))
    mesh_path = write_vtu(out / "mesh" / "mesh.vtu", mesh.mesh)
    m = mesh.summary()
    print(f"    {m['nodes']} nodes, {m['elements']} tets, {m['quality']['failing']['any']['count']} failing the "
          "seed's quality criteria")

    search = "CMA-ES" if gpu else "CMA-ES then L-BFGS-B"
    step(f"5/7 material fit (iso-hetero, E per tissue, {search}, {budget} forward solves; the first is the "
         "simulation with the starting materials)")
    def progress(done, total, best, phase):
        print(f"\r    {done}/{total} solves, best NMI {-best:.4f}", end="", flush=True)

    # on a CPU two generations of CMA-ES, then its local stage (three batched gradients): a
    # best-of-ten-draws alone left the fit unsettled (issue 82)
    settings = FitSettings(model="iso-hetero", free=("E",), edge_mm=fit_mm,
                           optimiser="cmaes" if gpu else "cmaes-local", budget=budget, population=6 if gpu else 5)
    clear_earlier_result(out / "fit")
    fit = fit_compressed_case(out / "case", out / "fit", settings, mesh_path=mesh_path, device=device,
                              progress=progress)
    print()
    errors = fit.landmark_errors["error_mm"]
    print(f"    best NMI {fit.result.best.nmi:.4f}; landmark error {errors['mean']:.2f} ± {errors['sd']:.2f} mm "
          f"(max {errors['max']:.2f}) against a displacement of {fit.landmark_errors['displacement_mm']['mean']:.1f} mm")

    # the whole library for up to three rounds on either device; on a CPU against the fixed floor
    # (measuring it solves the fit on eight times the tets: minutes on two cores)
    floor = "measured" if gpu else "fixed"
    step(f"6/7 model-discrepancy diagnosis: where the fit and the measurement disagree, which effect is missing "
         f"(the whole library; at most {DEMO_ROUNDS} rounds; model-error floor {floor}), added and refitted")
    clear_earlier_result(out / "diagnosis", "diagnosis.json", "diagnosis")
    # on a GPU the next measurement is designed for what the last round could not tell apart (every
    # acquisition of the library simulated: seconds there, a quarter of an hour on two CPU cores)
    diagnosis = run_diagnosis(out / "case", out / "fit", out / "diagnosis", rounds=DEMO_ROUNDS,
                              noise=NoiseModel(floor=floor),
                              settings=DiagnosisSettings(refine_iterations=2), device=device,
                              progress=lambda message: print(f"    {message}", flush=True),
                              design=() if gpu else None)
    for record in diagnosis.rounds:
        if record.get("after"):
            before, after = record["before"]["landmark_error_mm"], record["after"]["landmark_error_mm"]
            print(f"    round {record['round']}: added {record['added']}: landmark error {before['mean']:.2f} -> "
                  f"{after['mean']:.2f} mm (mean)")

    step("7/7 report")
    save_overview(out / "fit" / "predicted_overview.png", read_image(out / "fit" / "predicted.nrrd"), None,
                  compressed.landmarks, title="FE-predicted compressed MR at the fitted parameters; measured landmarks")
    path = _write_demo_report(out, case, compressed, truth, dice, m, fit, diagnosis, report,
                              time.perf_counter() - started, "GPU" if gpu else "CPU", clock)
    print(f"demo finished in {time.perf_counter() - started:.0f} s: report {path}; open {paths['mr']}, "
          f"{compressed_paths['measured']}, {seg_paths['labels']}, {mesh_path} and {out / 'fit' / 'predicted.nrrd'} "
          "in Slicer")


DEMO_CASE = 5  # Table 1 case 5: 716 cm3, isotropic truth (inside the fitted family)
DEMO_COMPRESSION = 0.4  # of the breast's LR thickness (Table 1's 19 % for this case barely engages friction)
DEMO_FRICTION = 0.6  # the plates' Coulomb mu hidden in the truth (the suite's)
DEMO_ROUNDS = 3  # of diagnose, add and refit, at most


def _diagnosis_section(diagnosis) -> str:
    """The demo report's diagnosis section: each round's verdict, before and after, the picture."""
    added = ", ".join(diagnosis.added) or "none"
    parts = [f"**Effects added: {added}. Final verdict: {diagnosis.final['sentence']}**", ""]
    for record in diagnosis.rounds:
        parts.append(f"Round {record['round']}: {record['diagnosis']['sentence']}")
        if record.get("after"):
            b, a = record["before"], record["after"]
            parts += ["", "| | before | after adding " + record["added"] + " |", "|---|---|---|",
                      f"| landmark error, mean (mm) | {b['landmark_error_mm']['mean']:.2f} | "
                      f"{a['landmark_error_mm']['mean']:.2f} |",
                      f"| landmark error, max (mm) | {b['landmark_error_mm']['max']:.2f} | "
                      f"{a['landmark_error_mm']['max']:.2f} |",
                      f"| NMI | {b['nmi']:.4f} | {a['nmi']:.4f} |"]
            if "residual_field" in b and "residual_field" in a:
                parts.append(f"| residual displacement field, mean (mm) | {b['residual_field']['mean_mm']:.2f} | "
                             f"{a['residual_field']['mean_mm']:.2f} |")
        if record.get("residual_picture"):
            parts += ["", f"![residual displacement field, round {record['round']}](diagnosis/{record['residual_picture']})"]
        parts.append("")
    return "\n".join(parts)


def identifiability_effects(case_dir: Path, fit_dir: Path) -> dict:
    """The library's effects sized to a fitted case (name -> effect), for their parameters' ranges."""
    from BreastBiomechLib.discrepancy.effects import library
    from BreastBiomechLib.discrepancy.fitted import load_fitted_case

    return {e.name: e for e in library(load_fitted_case(case_dir, fit_dir, device="cpu"))}


def identifiability_section(diagnosis, effects: dict) -> str:
    """What the demo's case could and could not have shown: per candidate of the last round, the
    share of its signature the fitted parameters reproduce and the smallest size its test would
    see, so that "no significant discrepancy" is not read as "nothing missing"."""
    from BreastBiomechLib.discrepancy.diagnosis import ABSORBED, not_identifiable

    last = diagnosis.rounds[-1]
    rows = []
    for c in last["diagnosis"]["candidates"]:
        effect = effects.get(c["name"])
        if c.get("skipped"):
            rows.append(f"| {c['title']} | - | - | not tested: {c['skipped']} |")
            continue
        by = c.get("absorbed_by") or {}
        absorbed = f"{c['absorbed']:.0%}" + (f" (chiefly {by['name']})" if by.get("name") else "")
        sizes = [f"{p.name} {'none' if d is None else f'{d:.3g} {p.unit}'.strip()} (range {p.lower:g} to {p.upper:g})"
                 for p, d in zip(effect.parameters, c.get("detectable") or [])] if effect is not None else []
        if c["absorbed"] >= ABSORBED:
            verdict = f"no: the fit takes it up as {by.get('name', 'its parameters')}"
        elif not_identifiable(c, effect):
            verdict = "no: too small to see at this case's noise, whatever its size"
        else:
            verdict = "yes, from that size on"
        rows.append(f"| {c['title']} | {absorbed} | {'; '.join(sizes) or '-'} | {verdict} |")
    return "\n".join([
        f"### What this case could and could not have shown (round {last['round']})", "",
        "Each candidate's share of its signature that the fitted parameters reproduce (at "
        f"{ABSORBED:.0%} or more no test of the residual can see it: it has been fitted as those "
        "parameters) and the smallest size its score test would detect with 80 % power at this case's "
        "noise (the diagnosis report's columns, docs/discrepancy.md):", "",
        "| effect | absorbed by the fit | smallest size its test would see | could this case show it |",
        "|---|---|---|---|", *rows])


def _next_measurement_section(diagnosis, device: str) -> str:
    """The design of the next measurement (on a GPU) or the command that makes it (on a CPU)."""
    from BreastBiomechLib.discrepancy.report import design_section

    if device == "GPU":
        return "\n".join(design_section(diagnosis)).replace("## The next measurement", "### The next measurement")
    return ("### The next measurement\n\nNot designed on a CPU: it simulates each acquisition of the library "
            "(compressions of -20 to +20 %, each plate moving alone, the plates turned) with the sensitivities of "
            "the candidates it would tell apart: 16 minutes on two cores for the CPU demo's case. `breastbiomech diagnose "
            "out/demo/case --fit out/demo/fit --out out/demo/diagnosis --resume --design --floor fixed` adds it to "
            "diagnosis/report.md (docs/design.md).")


def _fit_note(fit, diagnosis) -> str:
    """Whether the fit had settled, and its landmark error against the model-error floor the
    diagnosis assumes: an unfinished fit leaves a residual that the diagnosis then tests too."""
    from BreastBiomechLib.optimisation.run import SETTLED

    gain, solves = fit.result.recent_gain(), len(fit.result.evaluations)
    error = fit.landmark_errors["error_mm"]["mean"]
    floor = diagnosis.rounds[0]["floor"] if diagnosis.rounds else {}
    floor_mm = floor.get("rms_mm", floor.get("fixed_mm", float("nan")))
    against = f"the fitted model's landmark error ({error:.2f} mm mean) is {error / floor_mm:.1f} times the " \
              f"model-error floor the diagnosis assumes ({floor_mm:.2f} mm RMS)"
    if not gain <= SETTLED:
        return (f"**The fit had not settled**: its best NMI still rose by {gain:.4f} over the last half of its "
                f"{solves} solves, and {against}. Part of the residual the "
                "diagnosis below tests is the unfinished fit's (a missing effect and an unfinished fit both leave "
                "one); fit with more solves (`breastbiomech optimise --budget 60`, a GPU) before trusting a verdict.")
    return f"The fit had settled (its best NMI rose by {gain:.4f} over the last half of its solves); {against}."


def _write_demo_report(out: Path, case, compressed, truth, dice, mesh_summary, fit, diagnosis, report, seconds,
                       device, clock: StageClock) -> Path:
    """out/report.md: what each step made, with pictures (paths relative to ``out``)."""
    times = [t for _, t in report["steps"]] + [time.perf_counter()]
    rows = "\n".join(f"| {text} | {times[i + 1] - times[i]:.0f} |" for i, (text, _) in enumerate(report["steps"]))
    e, d = fit.landmark_errors["error_mm"], fit.landmark_errors["displacement_mm"]
    start = fit.result.evaluations[0]
    materials = "\n".join(
        f"| {name} | {values['E'] / 1e3:.1f} | {truth.materials.get(name, {}).get('E', float('nan')) / 1e3:.1f} |"
        for name, values in fit.result.materials.items())
    budget_note = ("The demo's budget on a CPU is small: `breastbiomech optimise` and `breastbiomech study` "
                   "(docs/optimisation.md, docs/validation.md) fit with hundreds of solves on a GPU."
                   if device == "CPU" else f"A GPU fit of {len(fit.result.evaluations)} solves.")
    text = f"""# BreastBiomech demo report

Made by `breastbiomech demo` on the {device} in {seconds:.0f} s. Everything below is in this folder.

| step | seconds |
|---|---|
{rows}

## Phantom and its compressed "measured" scan

Table 1 case {DEMO_CASE}: {case.summary['breast_volume_cm3']:.0f} cm³, glandular density
{case.summary['glandular_density']:.1%}; compressed by {truth.compression:.0%} between LR plates in a truth simulation
({compressed.summary['truth_tets']} tets of {truth.edge_mm:g} mm; {compressed.summary['solve_message']}) whose plates
hold the skin by Coulomb friction (mu {truth.friction:g}): an effect the fitted model leaves out, for the diagnosis to find.

![undeformed](case/overview.png)

![measured compressed](case/compressed/overview.png)

## Segmentation and mesh

Dice against the phantom's truth: {", ".join(f"{k} {v:.3f}" for k, v in dice.items())}.
Fitting mesh of the segmentation: {mesh_summary['nodes']} nodes, {mesh_summary['elements']} tets.

## Simulation and material fit

The first forward solve, with the starting materials, gave NMI {start.nmi:.4f} and a landmark error of
{start.landmark_mean_mm:.2f} mm (mean); after {len(fit.result.evaluations)} solves ({fit.result.stopped}) the best
NMI is {fit.result.best.nmi:.4f} and the landmark error {e['mean']:.2f} ± {e['sd']:.2f} mm (max {e['max']:.2f}),
for landmark displacements of {d['mean']:.1f} ± {d['sd']:.1f} mm (max {d['max']:.1f}). One voxel diagonal is 2.87 mm.

| material | fitted E (kPa) | truth E (kPa) |
|---|---|---|
{materials}

Fat's E is the reference (10 kPa). {budget_note}

![FE-predicted](fit/predicted_overview.png)

![convergence](fit/convergence.png)

{_fit_note(fit, diagnosis)}

## Model discrepancy: what the fitted model is missing

`breastbiomech diagnose` (docs/discrepancy.md) on the fit, never reading the truth: the residuals of the
landmarks and of the skin surface, the sensitivity of each candidate effect, score tests, refits and the verdict,
then the named effect added and the model refitted: the whole library for up to {DEMO_ROUNDS} rounds, with two
further Gauss-Newton iterations of the added effect. On a GPU against the model-error floor measured from the case; on a
CPU against the fixed floor (0.5 mm; measuring it solves the fit again on eight times the tets, minutes on two cores).
Everything is in `diagnosis/` (report.md, round-N.json, the residual fields as .nrrd).

{_diagnosis_section(diagnosis)}

{identifiability_section(diagnosis, identifiability_effects(out / 'case', out / 'fit'))}

{_next_measurement_section(diagnosis, device)}

## Where the time went

Wall seconds per kind of work up to this report, each without the kinds inside it (solving
counts inside the fit, the truth and the diagnosis alike; `breastbiomech bench demo --json` prints
them; stages.json holds the run's own).

{clock.table()}
"""
    return write_text_atomically(out / "report.md", text)


def add_parsers(sub) -> None:
    """Register the ``demo`` command on ``sub`` (argparse sub-parsers)."""
    p = sub.add_parser("demo", help="run the main job on the built-in phantom")
    p.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    p.add_argument("--device", type=device_argument, help="warp device (default: the GPU when there is one)")
    p.add_argument("--budget", type=positive_int, help="forward solves of the fit (default 19 on a CPU, 200 on a GPU)")
    p.add_argument("--truth-edge-mm", type=positive, help="the truth mesh's element size (mm; default 6 on a CPU, "
                                                          "2 on a GPU)")
    p.add_argument("--fit-edge-mm", type=positive, help="the fitting mesh's element size (mm; default 5 on a CPU, "
                                                        "4 on a GPU, its skin half of it there)")
    p.set_defaults(func=cmd_demo)
