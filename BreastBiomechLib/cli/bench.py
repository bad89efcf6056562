"""``breastbiomech bench``: benchmark figures (one JSON line with ``--json``); see
docs/benchmarks.md. Never asserts on time."""

from __future__ import annotations

import contextlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from BreastBiomechLib import __version__
from BreastBiomechLib.cli.common import (MODEL_CHOICES, device_argument, fraction, non_negative, non_negative_int,
                                         positive, positive_int)
from BreastBiomechLib.cli.gpu_usage import GpuUsage
from BreastBiomechLib.cohort import place
from BreastBiomechLib.discrepancy.suite import HIDDEN_EFFECTS, SuiteSettings
from BreastBiomechLib.discrepancy.suite.cases import HIDDEN_EFFECTS as HIDDEN
from BreastBiomechLib.discrepancy.suite.cases import SuiteCase
from BreastBiomechLib.discrepancy.suite.runner import run_case
from BreastBiomechLib.mesh.primitives import hemi_ellipsoid_mesh
from BreastBiomechLib.solver import DynamicRelaxation
from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression
from BreastBiomechLib.solver.warm import WarmStart
from BreastBiomechLib.timing import StageClock, clocked

BENCH_RADII_MM = (80.0, 70.0, 75.0)  # the benchmarks' hemi-ellipsoid (hemi_ellipsoid_compression's default)
# benchmarks that need only warp, NumPy and SciPy (the solver on its own hemi-ellipsoid meshes): they
# run on a machine without VTK, SimpleITK or TetGen, as a GPU node with warp installed
WITHOUT_VTK = ("solver", "unloaded")


def _hemi_ellipsoid_spacing(tets: int) -> float:
    """The grid spacing (mm) that gives the benchmarks' hemi-ellipsoid about ``tets`` elements."""
    return float((np.pi * 4 * np.prod(BENCH_RADII_MM) / tets) ** (1 / 3))


def bench_parameter_sets(base, batch: int) -> list:
    """The solver bench's ``batch`` parameter sets: ``base`` (an ``ElementMaterials``), then
    ``batch`` - 1 copies with mu and kappa scaled by factors drawn uniformly from 0.7-1.3 (seed 0),
    so that the models converge at different iterations."""
    factors = np.random.default_rng(0).uniform(0.7, 1.3, batch - 1)
    return [base] + [type(base)(base.mu * f, base.kappa * f, base.eta, base.fibre, base.density) for f in factors]


def _bench_solver(args) -> dict:
    """One forward solve (or a batch) of the hemi-ellipsoid compression case; figures as a dict."""
    import warp as wp

    from BreastBiomechLib.solver import DynamicRelaxation, solve_batch

    spacing = _hemi_ellipsoid_spacing(args.tets)
    settle = 0.25 * args.total_time if args.settle_time is None else args.settle_time
    model = hemi_ellipsoid_compression(spacing, compression=0.25, total_time=args.total_time, settle_time=settle)
    for plate in model.loading.plates:
        plate.friction = args.friction
    wp.init()
    device = wp.get_device(args.device)
    base = model.materials
    variants = bench_parameter_sets(base, args.batch)
    load = {} if args.load_iterations is None else {"load_iterations": args.load_iterations}
    relaxation = DynamicRelaxation(tolerance_mm=0.01, **load) if args.relaxation else None
    # compile the kernels once, outside the timing: a relaxation's own module too (its first solve
    # in a process compiled it inside the timed span, 1.1-1.3 s on the H200)
    warm = hemi_ellipsoid_compression(20.0, total_time=0.05, settle_time=0.0)
    workers = None
    if device.is_cpu:  # the batch's worker processes (solver/cpu_pool.py), started outside the timing
        from BreastBiomechLib.solver.cpu_pool import cpu_workers

        workers = min(args.cpu_workers, args.batch) if args.cpu_workers else cpu_workers(args.batch)
    solve_batch(warm, [warm.materials] * (workers or 1), device=device, cpu_workers=workers,
                relaxation=DynamicRelaxation(max_iterations=1200) if args.relaxation else None)
    start = None
    if args.warm_start is not None:  # a fit's nearby parameter set, solved outside the timing
        if relaxation is None:
            raise ValueError("--warm-start is a start of dynamic relaxation: add --relaxation")
        nearby = type(base)(base.mu * args.warm_start, base.kappa, base.eta, base.fibre, base.density)
        start = solve_batch(model, [nearby], device=device, relaxation=relaxation)[0]
        if not start.ok:
            raise RuntimeError(f"the warm start's solve failed: {start.message}")
    started = time.perf_counter()
    solutions = solve_batch(model, variants, device=device, relaxation=relaxation,
                            steady_state_mm=args.steady_state_mm, cpu_workers=workers,
                            warm_start=None if start is None else WarmStart.from_solution(start))
    wall = time.perf_counter() - started
    s = solutions[0]
    memory_mb = None
    if device.is_cuda:  # device memory in use after the solve (warp's pool included)
        memory_mb = round((device.total_memory - device.free_memory) / 2**20, 1)
    n, m = len(model.mesh.nodes), len(model.mesh.tets)
    bytes_per_step = args.batch * (296 * m + 70 * n)  # reads/writes/atomics per step, see docs
    return {
        "benchmark": "solver", "device": str(device), "device_name": getattr(device, "name", ""),
        "nodes": n, "tets": m, "batch": args.batch, "formulation": model.formulation, "friction": args.friction,
        "method": "dynamic relaxation" if args.relaxation else "physical time",
        "load_iterations": relaxation.load_iterations if relaxation else None,
        "warm_start_mu_factor": args.warm_start, "warm_start_steps": None if start is None else start.steps,
        "estimated_error_mm": s.estimated_error_mm,
        "steps": s.steps, "time_step_s": s.time_step, "simulated_s": s.steps * s.time_step,
        "wall_s": round(wall, 4), "solve_wall_s": round(s.wall_time, 4),
        "us_per_step": round(1e6 * s.wall_time / s.steps, 3),
        "us_per_step_per_model": round(1e6 * s.wall_time / s.steps / args.batch, 3),
        "bytes_per_step": bytes_per_step,
        "floor_us_per_step_at_3350GBs": round(bytes_per_step / 3.35e9 * 1e6 / 1e3, 3),
        "status": s.status, "message": s.message, "ke_ie_end_of_loading": s.ke_ie_at_end_of_loading,
        "plate_force_N": float(np.linalg.norm(s.plate_forces[0])),
        "max_displacement_mm": float(np.abs(s.displacement).max()),
        "device_memory_in_use_mb": memory_mb,
        "cpu_workers": workers, "models_per_s": round(args.batch / wall, 4),
    }


def _bench_unloaded(args) -> dict:
    """The unloaded reference state of the hemi-ellipsoid breast of about ``--tets`` tets imaged
    prone (gravity 9.81 m/s^2 anterior) with the seed's chest wall: iterations, residual, wall
    time and the gravity sag."""
    import warp as wp

    from BreastBiomechLib.solver.unloaded import unloaded_shape

    spacing = _hemi_ellipsoid_spacing(args.tets)
    model = hemi_ellipsoid_compression(spacing)
    wp.init()
    device = wp.get_device(args.device)
    warm = hemi_ellipsoid_compression(20.0, total_time=0.05, settle_time=0.0)
    unloaded_shape(warm, (0.0, -9.81, 0.0), tolerance_mm=0.5, device=device)  # compile outside the timing
    tolerance = 0.02 if args.tolerance_mm is None else args.tolerance_mm
    started = time.perf_counter()
    unloaded = unloaded_shape(model, (0.0, -9.81, 0.0), tolerance_mm=tolerance, device=device)
    wall = time.perf_counter() - started
    return {"benchmark": "unloaded", "device": str(device), "device_name": getattr(device, "name", ""),
            "nodes": len(model.mesh.nodes), "tets": len(model.mesh.tets), "gravity": [0.0, -9.81, 0.0],
            "material": "E 10 kPa, nu 0.49", "tolerance_mm": tolerance, "iterations": unloaded.iterations,
            "residual_mm": unloaded.residual_mm, "residual_history_mm": [round(r, 5) for r in unloaded.history],
            "largest_sag_mm": unloaded.largest_sag_mm,
            "wall_s": round(wall, 3)}


EFFECT_SIZES = {"friction 0.5": {"friction": 0.5}, "gravity 9.81 m/s^2 prone": {"gravity": [0.0, -9.81, 0.0]},
                "sliding chest wall": {"chest_wall": "sliding"}, "skin 50 kPa / 2 mm": {"skin": [50e3, 2.0]},
                "tilt 0.5 deg": {"plate_tilt_deg": [[0.0, 0.5], [0.0, 0.0]]}}


def _bench_effects(args) -> dict:
    """How far the compressed landmarks of Table 1 case ``--cases[0]`` move when each effect the
    seed's model leaves out is switched on alone at a realistic size (the truth simulation with
    the effect vs without, one truth mesh of ``--truth-edge-mm``): the signal a discrepancy
    diagnosis has to find. Landmark shifts in mm (17 landmarks), wall times in s."""
    from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels
    from BreastBiomechLib.phantom import generate_phantom, table1_case
    from BreastBiomechLib.phantom.compressed import compress_phantom, table1_truth

    number = args.cases[0]
    case = generate_phantom(table1_case(number))
    truth = replace(table1_truth(number), edge_mm=args.truth_edge_mm)
    started = time.perf_counter()
    mesh = mesh_labels(case.labels, MeshSettings(edge_mm=truth.edge_mm), nipple_mm=case.landmarks.position("nipple")).mesh
    figures = {"benchmark": "effects", "case": number, "truth_tets": len(mesh.tets), "truth_edge_mm": truth.edge_mm,
               "mesh_s": round(time.perf_counter() - started, 1), "effects": {}}
    started = time.perf_counter()
    plain = compress_phantom(case, truth, device=args.device, mesh=mesh)
    figures["seed_model"] = {"seconds": round(time.perf_counter() - started, 1),
                             "landmark_displacement_mm": float(np.linalg.norm(
                                 plain.landmarks.positions - case.landmarks.positions, axis=1).mean())}
    for name, change in EFFECT_SIZES.items():
        started = time.perf_counter()
        try:
            compressed = compress_phantom(case, replace(truth, **change), device=args.device, mesh=mesh)
        except (RuntimeError, ValueError) as error:
            figures["effects"][name] = {"error": str(error)}
            continue
        shift = np.linalg.norm(compressed.landmarks.positions - plain.landmarks.positions, axis=1)
        figures["effects"][name] = {"landmark_shift_mean_mm": round(float(shift.mean()), 3),
                                    "landmark_shift_max_mm": round(float(shift.max()), 3),
                                    "seconds": round(time.perf_counter() - started, 1),
                                    "solve": compressed.summary["solve_message"]}
    return figures


SUITE_CASE_DEFAULTS = {"truth_edge_mm": 3.0, "fit_edge_mm": 6.0, "fit_budget": 60}  # effects, diagnose, cohort


def _bench_demo(args) -> dict:
    """`breastbiomech demo` timed stage by stage (:mod:`~BreastBiomechLib.timing`) in ``--out``
    (replaced as the demo replaces its results) or a temporary folder: the wall seconds of each
    kind of work, its share, and the solver's share of the whole."""
    from BreastBiomechLib.cli.demo import run_demo

    with tempfile.TemporaryDirectory(prefix="bench-demo-") as scratch:
        out = Path(args.out) if args.out else Path(scratch) / "demo"
        with contextlib.redirect_stdout(sys.stderr):  # the demo's progress; stdout keeps the figures
            clock = run_demo(out, args.device, args.fit_budget, args.truth_edge_mm, args.fit_edge_mm)
        return {"benchmark": "demo", "version": __version__, "device": args.device or "default",
                "meshes": json.loads((out / "stages.json").read_text()).get("meshes"),
                **staged_figures(clock, out / "diagnosis")}


def staged_figures(clock: StageClock, diagnosis_dir: Path) -> dict:
    """The figures of a timed run that ended with the diagnosis in ``diagnosis_dir``: wall
    seconds, the solver's share, each stage's seconds, and the diagnosis's final verdict, effects
    added and rounds (from its diagnosis.json)."""
    record = json.loads((Path(diagnosis_dir) / "diagnosis.json").read_text())
    return {"wall_s": round(clock.wall_s, 1), "solving_share": round(clock.share("solving"), 3),
            "stages": clock.to_dict()["stages"], "unstaged_s": round(clock.unstaged_s, 1),
            "verdict": {"final": record["final"], "added": record["added"], "rounds": len(record["rounds"])}}


def _bench_diagnose(args) -> dict:
    """One hidden-effect suite case timed stage by stage: Table 1 anatomy ``--cases[0]`` with
    ``--hidden`` hidden in its truth, segmented, meshed, fitted and diagnosed as the suite does it
    (:func:`~BreastBiomechLib.discrepancy.suite.runner.run_case`), in ``--out`` (kept; a rerun
    times only what is not done) or a temporary folder. Seconds per stage; the diagnosis's
    rounds with their solves and seconds (no residual fields, as in the suite); the verdicts."""
    settings = SuiteSettings(spacing_mm=tuple(args.voxel_mm), truth_edge_mm=args.truth_edge_mm,
                             fit_edge_mm=args.fit_edge_mm, fit_budget=args.fit_budget,
                             fit_population=min(12, args.fit_budget), rounds=args.rounds)
    case = SuiteCase(args.cases[0], HIDDEN_EFFECTS[args.hidden])
    with tempfile.TemporaryDirectory(prefix="bench-diagnose-") as scratch:
        out = Path(args.out) if args.out else Path(scratch)
        started = time.perf_counter()
        with clocked(StageClock(synchronise=_synchronise(args.device))) as clock:
            result = run_case(case, out, settings, args.device)
        wall = time.perf_counter() - started
        rounds = json.loads((out / case.name / "diagnosis" / "diagnosis.json").read_text())["rounds"]
    return {"benchmark": "diagnose", "version": __version__, "device": args.device or "default",
            "case": case.name, "settings": {"voxel_mm": list(settings.spacing_mm),
                                            "truth_edge_mm": settings.truth_edge_mm,
                                            "fit_edge_mm": settings.fit_edge_mm, "fit_budget": settings.fit_budget,
                                            "rounds": settings.rounds},
            "truth_tets": result["anatomy_figures"]["truth_mesh"]["tets"],
            "fitting_tets": result["anatomy_figures"]["fitting_mesh"]["tets"],
            "anatomy_s": round(sum(f["seconds"] for f in result["anatomy_figures"].values()), 1),
            "seconds": result["seconds"],
            "rounds": [{"verdict": r["diagnosis"]["verdict"], "added": r.get("added"), "solves": r["diagnosis"]["solves"],
                        "seconds": r["seconds"]} for r in rounds],
            "right": result["correct"], "landmark_error_before_mm": result["landmark_error_before_mm"],
            "landmark_error_after_mm": result.get("landmark_error_after_mm"), "wall_s": round(wall, 1),
            "solving_share": round(clock.share("solving"), 3), "stages": clock.to_dict()["stages"]}


def _synchronise(device):
    """``warp.synchronize`` where ``device`` (a warp device name, or None: warp's default) is a
    GPU, so that each stage holds its own kernels' time; None on a CPU."""
    import warp as wp

    wp.init()
    return wp.synchronize if wp.get_device(device).is_cuda else None


def _fit_grid(image, grid):
    """``image`` padded (edge voxels repeated: the chest and the air continue) or cropped
    symmetrically to ``grid`` voxels."""
    import SimpleITK as sitk

    change = [g - s for g, s in zip(grid, image.GetSize())]
    grow = [max(c, 0) for c in change]
    image = sitk.ZeroFluxNeumannPad(image, [g // 2 for g in grow], [g - g // 2 for g in grow])
    shrink = [max(-c, 0) for c in change]
    return sitk.Crop(image, [s // 2 for s in shrink], [s - s // 2 for s in shrink])


def _bench_segment(args) -> dict:
    """Segment a phantom (``--volume-cm3``, ``--tumour-mm``, ``--snr``, ``--bias``, ``--seed``)
    from its written seed points, its volume padded or cropped to ``--grid`` when given; Dice
    against the ground truth and the wall time (the phantom's generation is not timed)."""
    from BreastBiomechLib.phantom import PhantomParameters, generate_phantom
    from BreastBiomechLib.phantom.files import SEED_COUNTS
    from BreastBiomechLib.phantom.seeds import seed_points
    from BreastBiomechLib.segmentation import dice_per_tissue, segment_tissues

    params = PhantomParameters(seed=args.seed, volume_cm3=args.volume_cm3, tumour_diameter_mm=args.tumour_mm,
                               snr=args.snr, bias_strength=args.bias)
    case = generate_phantom(params)
    image, labels = case.image, case.labels
    if args.grid:
        image, labels = _fit_grid(image, args.grid), _fit_grid(labels, args.grid)
    muscle = seed_points(labels, "muscle", SEED_COUNTS["muscle"]).positions
    tumour = seed_points(labels, "tumour", SEED_COUNTS["tumour"]).positions if args.tumour_mm > 0 else None
    started = time.perf_counter()
    result = segment_tissues(image, muscle, tumour)
    wall = time.perf_counter() - started
    return {"benchmark": "segment", "version": __version__, "machine": platform.machine(), "cores": os.cpu_count(),
            "grid": list(image.GetSize()), "voxels": int(image.GetNumberOfPixels()),
            "snr": args.snr, "bias": args.bias, "seed": args.seed, "tumour_mm": args.tumour_mm,
            "wall_s": round(wall, 2), "stages_s": result.summary["seconds"],
            "em_iterations": result.summary["em"]["iterations"],
            "dice": {k: round(v, 4) for k, v in dice_per_tissue(result.labels, labels).items()}}


def _bench_warp(args) -> dict:
    """Warp a synthetic image through a 25 % compression of the hemi-ellipsoid mesh (``--tets``)
    onto a ``--grid`` (default 256 x 256 x 100) covering it, and compare the result with the
    image by NMI and NCC, ``--repeat`` times; median and best milliseconds per call after a
    warm-up call (kernel compilation)."""
    import SimpleITK as sitk
    import warp as wp

    from BreastBiomechLib.similarity import Similarity
    from BreastBiomechLib.warping import ImageWarper

    spacing = _hemi_ellipsoid_spacing(args.tets)
    mesh = hemi_ellipsoid_mesh(BENCH_RADII_MM, spacing)
    grid = args.grid or (256, 256, 100)
    low, high = mesh.nodes.min(axis=0) - 5.0, mesh.nodes.max(axis=0) + 5.0
    voxel = (high - low) / (np.array(grid) - 1)
    k, j, i = np.meshgrid(*[np.arange(n) for n in grid[::-1]], indexing="ij")
    values = (500 + 300 * np.sin(i / 9.0) * np.cos(j / 13.0) + 150 * np.sin(k / 5.0)).astype(np.float32)
    image = sitk.GetImageFromArray(values)
    image.SetOrigin(tuple(low))
    image.SetSpacing(tuple(voxel))
    centre = mesh.nodes.mean(axis=0)
    squeeze = np.diag([0.75, 1.0, 1.0 / 0.75])  # 25 % compression along x, volume kept
    displacement = (mesh.nodes - centre) @ (squeeze - np.eye(3)).T
    wp.init()
    device = wp.get_device(args.device)
    warper = ImageWarper(mesh, image, image, device=device)
    similarity = Similarity(image, bins=64, device=device)

    def timed(call):
        call()
        wp.synchronize_device(device)
        times = []
        for _ in range(args.repeat):
            started = time.perf_counter()
            call()
            wp.synchronize_device(device)
            times.append(1000 * (time.perf_counter() - started))
        return round(float(np.median(times)), 3), round(float(np.min(times)), 3)

    warp_ms = timed(lambda: warper.warp(displacement))
    predicted = warper.warp(displacement)
    nmi_ms = timed(lambda: similarity.nmi(predicted))
    ncc_ms = timed(lambda: similarity.ncc(predicted))
    inside = int(np.count_nonzero(sitk.GetArrayFromImage(warper.predict(displacement).inside)))
    return {"benchmark": "warp", "version": __version__, "device": str(device),
            "device_name": getattr(device, "name", ""), "nodes": len(mesh.nodes), "tets": len(mesh.tets),
            "grid": list(grid), "voxels": int(np.prod(grid)), "inside_voxels": inside,
            "warp_ms_median": warp_ms[0], "warp_ms_best": warp_ms[1],
            "nmi_ms_median": nmi_ms[0], "nmi_ms_best": nmi_ms[1], "ncc_ms_median": ncc_ms[0],
            "ncc_ms_best": ncc_ms[1], "nmi": round(similarity.nmi(predicted), 6), "repeat": args.repeat}


def _bench_mesh(args) -> dict:
    """Mesh a phantom of ``--volume-cm3`` breast tissue (seed 1 preset otherwise) at
    ``--edge-mm``, its label map padded (edge voxels repeated: the chest continues) or cropped
    to ``--grid`` voxels when given; figures as a dict (the phantom's generation is not timed)."""
    from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels
    from BreastBiomechLib.phantom import PhantomParameters, generate_phantom

    case = generate_phantom(PhantomParameters(volume_cm3=args.volume_cm3))
    labels = _fit_grid(case.labels, args.grid) if args.grid else case.labels
    started = time.perf_counter()
    result = mesh_labels(labels, MeshSettings(edge_mm=args.edge_mm))
    wall = time.perf_counter() - started
    summary = result.summary()
    return {"benchmark": "mesh", "version": __version__, "machine": platform.machine(), "cores": os.cpu_count(),
            "breast_volume_cm3": round(case.summary["breast_volume_cm3"], 1), "grid": list(labels.GetSize()), "voxels": int(labels.GetNumberOfPixels()),
            "edge_mm": args.edge_mm, "nodes": summary["nodes"], "tets": summary["elements"],
            "wall_s": round(wall, 2), "stages_s": summary["seconds"],
            "failing_elements": summary["quality"]["failing"]["any"]["count"],
            "dihedral_min_deg": round(summary["quality"]["dihedral_min_deg"], 2),
            "elements_per_tissue": summary["elements_per_tissue"],
            "dice": {k: round(v["dice"], 4) for k, v in summary["tissue_representation"].items()}}


BENCH_TRUTH = {"glandular.E": 25e3, "muscle.E": 80e3, "tumour.E": 120e3, "fat.nu": 0.495, "glandular.nu": 0.49,
               "muscle.nu": 0.48, "tumour.nu": 0.495, "fat.eta": 4e3, "glandular.eta": 1e3, "muscle.eta": 2e4,
               "tumour.eta": 1e3}  # bench optimise's truth: 4 tissues x (E, nu, eta), fat's E the reference


def bench_fitting_problem(radii_mm=(70.0, 60.0, 65.0), element_mm: float = 4.0, voxel_mm=(1.0, 1.0, 2.5),
                          relaxation=None, device=None, measured: bool = True, warm_starts: bool = False,
                          pull_corners: bool = False):
    """The fitting problem ``bench optimise`` fits: the aniso-hetero space (4 tissues x E, nu,
    eta; fat's E the reference) on the synthetic breast of ``radii_mm`` in cubes of
    ``element_mm`` (10 mm of muscle, a tumour of 0.3 x the LR radius) imaged at ``voxel_mm``,
    whose measured image is the prediction at :data:`BENCH_TRUTH` (``measured`` False: the
    undeformed image stands in, for solves that need no similarity; ``warm_starts``: see
    :class:`~BreastBiomechLib.optimisation.FittingProblem`; ``pull_corners``: the stairs'
    protruding corners moved onto the ellipsoid, see
    :func:`~BreastBiomechLib.optimisation.synthetic.synthetic_case`)."""
    from BreastBiomechLib.optimisation import FittingProblem, ParameterSpace
    from BreastBiomechLib.optimisation.synthetic import measured_at, synthetic_case

    case = synthetic_case(tuple(radii_mm), element_mm=element_mm, voxel_mm=tuple(voxel_mm), muscle_mm=10.0,
                          tumour_mm=0.3 * radii_mm[0], pull_corners=pull_corners)
    space = ParameterSpace.for_model("aniso-hetero", ["fat", "glandular", "muscle", "tumour"])
    image = measured_at(case, space, BENCH_TRUTH, relaxation, device=device) if measured else case.undeformed
    return FittingProblem(space, case.mesh, case.undeformed, image, case.planes, relaxation=relaxation, device=device,
                          warm_starts=warm_starts)


def _bench_optimise(args) -> dict:
    """An end-to-end aniso-hetero fit (4 tissues x E, nu, eta; fat's E the reference) of the
    synthetic breast (optimisation.synthetic: ``--radii``, ``--element-mm``, ``--voxel-mm``)
    whose measured image is the prediction at :data:`BENCH_TRUTH`, within ``--budget`` solves
    by ``--optimiser``; the case's set-up is not timed. The mesh's protruding stair corners are
    moved onto its ellipsoid unless ``--stair-corners`` (see :func:`bench_fitting_problem`)."""
    from BreastBiomechLib.optimisation import optimise

    relaxation = DynamicRelaxation(tolerance_mm=0.01 if args.tolerance_mm is None else args.tolerance_mm)
    problem = bench_fitting_problem(args.radii, args.element_mm, args.voxel_mm, relaxation, args.device,
                                    warm_starts=args.warm_starts, pull_corners=not args.stair_corners)
    space = problem.space
    started = time.perf_counter()
    result = optimise(problem, args.optimiser, budget=args.budget, seed=args.seed, out_dir=args.out,
                      population=args.population)
    seconds = time.perf_counter() - started
    problem.start_fit()  # the truth solved cold, as its measured image was made
    truth = problem.evaluate(space.unit(BENCH_TRUTH))[0]
    errors = {key: round(abs(value / BENCH_TRUTH[key] - 1.0), 4) for key, value in result.best.values.items()}
    best_so_far = np.maximum.accumulate([e.nmi if e.status == "completed" else 0.0 for e in result.evaluations])
    quarters = sorted({max(1, round(q * len(best_so_far))) for q in (0.25, 0.5, 0.75, 1.0)})
    return {"benchmark": "optimise", "version": __version__, "device": str(problem.warper.device),
            "optimiser": args.optimiser, "warm_starts": args.warm_starts, "pull_corners": not args.stair_corners,
            "tets": len(problem.mesh.tets), "nodes": len(problem.mesh.nodes),
            "voxels": int(problem.similarity.voxels), "free_parameters": space.dimension,
            "budget": args.budget, "evaluations": len(result.evaluations), "stopped": result.stopped,
            "failed": sum(result.failures.values()), "failed_by_status": result.failures,
            "seconds": round(seconds, 2), "seconds_per_evaluation": round(seconds / len(result.evaluations), 4),
            "best_nmi": round(result.best.nmi, 5), "truth_nmi": round(truth.nmi, 5),
            "best_nmi_after": {str(n): round(float(best_so_far[n - 1]), 5) for n in quarters},
            "max_relative_error": max(errors.values()), "relative_errors": errors}


def _study_differences(rows, reference) -> dict:
    """How far a study's fits (``read_study`` rows) are from a reference study's of the same
    cases and models: the largest absolute NMI and objective differences, the largest relative
    difference of any fitted E, nu or eta, the fits whose solve counts differ, and the fits found
    in only one of the two."""
    mine, theirs = ({(r.case, r.model, r.optimiser): r for r in study} for study in (rows, reference))
    shared = sorted(mine.keys() & theirs.keys())
    nmi = objective = material = 0.0
    for key in shared:
        a, b = mine[key], theirs[key]
        nmi, objective = max(nmi, abs(a.nmi - b.nmi)), max(objective, abs(a.objective - b.objective))
        for tissue, values in a.materials.items():
            for name, value in values.items():
                other = b.materials.get(tissue, {}).get(name)
                if other is None:
                    material = float("inf")
                elif value != other:
                    material = max(material, abs(value - other) / max(abs(value), abs(other)))
    return {"nmi": nmi, "objective": objective, "materials_relative": material,
            "fits_with_other_solve_counts": sum(mine[k].evaluations != theirs[k].evaluations for k in shared),
            "fits_in_one_only": sorted("/".join(k) for k in mine.keys() ^ theirs.keys())}


def _worker_timeline(outcomes, started_at: float) -> dict:
    """Per worker of a cohort run: its tasks, the seconds it spent in them, and when (s after the
    run started) its first task started and its last one ended — the cluster's start and the
    run's tail, where workers idle. (Tasks that raised on a cluster, which do not say where they
    ran, are left out.)"""
    timeline: dict = {}
    for outcome in (o for o in outcomes if o.worker):
        entry = timeline.setdefault(outcome.worker, {"tasks": 0, "busy_seconds": 0.0, "first_start_s": None,
                                                     "last_end_s": 0.0})
        start = outcome.started_at - started_at
        entry["tasks"] += 1
        entry["busy_seconds"] = round(entry["busy_seconds"] + outcome.seconds, 1)
        entry["first_start_s"] = round(start if entry["first_start_s"] is None else min(entry["first_start_s"], start), 1)
        entry["last_end_s"] = round(max(entry["last_end_s"], start + outcome.seconds), 1)
    return dict(sorted(timeline.items()))


def _bench_cohort(args) -> dict:
    """The study of ``--case-dirs`` (``--models``, ``--budget`` solves per fit, fitting meshes of
    ``--fit-edge-mm``) run each way of ``--modes`` into a fresh folder: "serial" (every task in
    this process), "dask" (a local cluster of ``--workers``, default one per GPU or core; several
    counts run the mode once per count, "dask-W"), "processes" (one ``breastbiomech study CASE
    --workers 0`` process per case, side by side: how the study ran before it had Dask). Per mode:
    wall seconds, fits per hour, the failed tasks (or processes) with their errors, each GPU's
    utilisation over the run (where nvidia-smi exists), and how far its fits are from the first
    mode's (NMI, objective, materials, solves; on a GPU, atomic sums make NMI differ in its last
    digits from run to run, on the CPU the rows are equal), and per worker its tasks, busy
    seconds and first start and last end (``workers``) and each task's key, worker, start (s
    after the run's start) and seconds (``tasks``; both empty for "processes")."""
    from BreastBiomechLib.optimisation.study import StudySettings, read_study, run_study

    budgets = {model: args.budget for model in args.models}
    settings = StudySettings(models=tuple(args.models), budgets=budgets, edge_mm=args.fit_edge_mm)
    base = Path(args.out or tempfile.mkdtemp(prefix="bench-cohort-"))
    figures = {"benchmark": "cohort", "version": __version__, "cases": len(args.case_dirs),
               "models": list(args.models), "budget": args.budget, "fit_edge_mm": args.fit_edge_mm, "modes": {}}
    worker_counts = args.workers or [None]
    runs = [(f"dask-{w}" if len(worker_counts) > 1 else mode, w) if mode == "dask" else (mode, None)
            for mode in args.modes for w in (worker_counts if mode == "dask" else [None])]
    reference = None
    for name, workers in runs:
        out = base / name
        if out.exists():
            raise FileExistsError(f"{out} exists: give a new --out (the benchmark times fits from scratch)")
        started, started_at = time.perf_counter(), time.time()
        outcomes = []
        with GpuUsage() as usage:
            if name == "processes":
                device = ["--device", args.device] if args.device else []
                processes = [subprocess.Popen([sys.executable, "-c", "import sys; from BreastBiomechLib.cli import main; "
                                               "sys.exit(main())", "study", str(case), "--out", str(out), "--models",
                                               *args.models, "--budget", *(f"{m}={args.budget}" for m in args.models),
                                               "--edge-mm", str(args.fit_edge_mm), "--workers", "0", "--quiet",
                                               *device], stdout=subprocess.DEVNULL) for case in args.case_dirs]
                codes = [process.wait() for process in processes]
                failed = {str(case): f"exit code {code}" for case, code in zip(args.case_dirs, codes) if code}
                where = f"{len(processes)} processes side by side"
            else:
                placement = place(None, 0 if name == "serial" else workers, args.device)
                run = run_study(args.case_dirs, out, settings, placement=placement)
                failed = {o.key: o.error for o in run.failed}
                outcomes = run.outcomes
                where = placement.describe()
        seconds = time.perf_counter() - started
        rows = read_study(out)
        reference = rows if reference is None else reference
        figures["modes"][name] = {"where": where, "fits": len(rows), "failed": failed, "seconds": round(seconds, 1),
                                  "fits_per_hour": round(3600 * len(rows) / seconds, 1), "gpu_usage": usage.summary,
                                  "workers": _worker_timeline(outcomes, started_at),
                                  "tasks": [[o.key, o.worker, round(o.started_at - started_at, 1), round(o.seconds, 1)]
                                            for o in sorted(outcomes, key=lambda o: o.started_at) if o.worker],
                                  "differences_from_first_mode": _study_differences(rows, reference)}
    first = next(iter(figures["modes"].values()))["seconds"]
    for entry in figures["modes"].values():
        entry["seconds_over_first_mode"] = round(entry["seconds"] / first, 3)
    figures["device"] = args.device or "default"
    return figures


def cmd_bench(args) -> int:
    if args.what == "solver":
        figures = _bench_solver(args)
        if args.json:
            print(json.dumps(figures))
        else:
            for key, value in figures.items():
                print(f"{key:32s} {value}")
        return 0
    if args.family is not None and not args.sweep:
        raise ValueError("--family applies to --sweep only")
    if args.sweep:
        if args.what not in ("segment", "mesh"):
            raise ValueError(f"--sweep applies to segment and mesh only, not to {args.what}")
        from BreastBiomechLib.cli.sweeps import MESH_EDGES_MM, run_sweep

        if args.compression is not None and args.what != "mesh":
            raise ValueError("--compression applies to the mesh sweep only")
        figures = run_sweep(args.what, args.variants, args.processes, args.out, args.edges or MESH_EDGES_MM,
                            args.compression, args.device, args.family or "anatomy")
        print(json.dumps(figures) if args.json else "\n".join(f"{k:24s} {v}" for k, v in figures.items() if k != "rows"))
        return 0
    if args.what != "demo":  # the demo's meshes and budget default to its device's (cli/demo.py, DemoMeshes)
        for name, default in SUITE_CASE_DEFAULTS.items():
            if getattr(args, name) is None:
                setattr(args, name, default)
    if args.what in ("mesh", "segment", "warp", "optimise", "unloaded", "effects", "demo", "diagnose", "cohort"):
        figures = {"mesh": _bench_mesh, "segment": _bench_segment, "warp": _bench_warp, "optimise": _bench_optimise,
                   "unloaded": _bench_unloaded, "effects": _bench_effects, "demo": _bench_demo,
                   "diagnose": _bench_diagnose, "cohort": _bench_cohort}[args.what](args)
        print(json.dumps(figures) if args.json else "\n".join(f"{k:24s} {v}" for k, v in figures.items()))
        return 0
    if args.what == "phantom":
        from BreastBiomechLib.phantom import generate_phantom, table1_case

        figures = {"benchmark": "phantom", "version": __version__, "machine": platform.machine(),
                   "python": platform.python_version(), "cases": {}}
        for number in args.cases:
            started = time.perf_counter()
            case = generate_phantom(table1_case(number))
            figures["cases"][number] = {
                "seconds": round(time.perf_counter() - started, 2),
                "breast_volume_cm3": round(case.summary["breast_volume_cm3"], 1),
                "voxels": int(case.image.GetNumberOfPixels()),
            }
        if args.json:
            print(json.dumps(figures))
        else:
            for number, f in figures["cases"].items():
                print(f"case {number}: {f['seconds']:.1f} s, {f['voxels']} voxels, {f['breast_volume_cm3']} cm3")
    return 0


def add_parsers(sub) -> None:
    """Register the ``bench`` command on ``sub`` (argparse sub-parsers)."""
    p = sub.add_parser("bench", help="print benchmark figures")
    p.add_argument("what", choices=["phantom", "segment", "mesh", "solver", "unloaded", "effects", "warp", "optimise",
                                    "demo", "diagnose", "cohort"], help="what to time")
    p.add_argument("--cases", type=int, nargs="+", default=[1, 2, 3, 4, 5], choices=range(1, 6),
                   help="Table 1 cases (phantom; effects, diagnose: the first)")
    p.add_argument("--truth-edge-mm", type=positive,
                   help="effects, diagnose: the truth mesh's element size (mm; default 3); demo: its truth mesh's "
                        "(default its device's)")
    p.add_argument("--hidden", choices=sorted(HIDDEN), default="friction",
                   help="diagnose: the effect hidden in the truth (a suite case's, default friction)")
    p.add_argument("--fit-edge-mm", type=positive,
                   help="diagnose, cohort: the fitting mesh's element size (mm; default 6); demo: its fitting "
                        "mesh's (default its device's)")
    p.add_argument("--fit-budget", type=positive_int,
                   help="diagnose: the material fit's forward solves (default 60); demo: its fit's (default its "
                        "device's)")
    p.add_argument("--rounds", type=positive_int, default=3, help="diagnose: rounds at most")
    p.add_argument("--tets", type=positive_int, default=160_000, help="solver, warp: about this many tets (hemi-ellipsoid)")
    p.add_argument("--repeat", type=positive_int, default=10, help="warp: timed calls (median and best reported)")
    p.add_argument("--batch", type=positive_int, default=1, help="solver: parameter sets solved in one launch")
    p.add_argument("--device", type=device_argument, default=None, help="solver, warp: cuda, cpu or a warp device name (default: warp's)")
    p.add_argument("--total-time", type=positive, default=1.0, help="solver: loading time in s (+25%% settling)")
    p.add_argument("--settle-time", type=non_negative, default=None, help="solver: settling time in s (default 25%% of loading)")
    p.add_argument("--steady-state-mm", type=positive, default=None,
                   help="solver, physical time: stop settling once this close to rest (mm)")
    p.add_argument("--relaxation", action="store_true", help="solver: dynamic relaxation (tolerance 0.01 mm)")
    p.add_argument("--friction", type=non_negative, default=0.0, help="solver: the plates' Coulomb friction mu")
    p.add_argument("--warm-starts", action="store_true",
                   help="optimise: each batch of solves starts at the best evaluation's equilibrium (see "
                        "docs/benchmarks.md: not yet faster on this benchmark)")
    p.add_argument("--cpu-workers", type=positive_int, default=None, metavar="N",
                   help="solver on a CPU device: the batch's variants split over N worker processes (default "
                        "BREASTBIOMECH_CPU_WORKERS, else the cores; 1: this process alone)")
    p.add_argument("--warm-start", type=positive, default=None, metavar="FACTOR",
                   help="solver, dynamic relaxation: start at the equilibrium of the same breast with its shear "
                        "modulus times FACTOR (a fit's nearby parameter set; solved first, outside the timing)")
    p.add_argument("--load-iterations", type=positive_int, default=None,
                   help="solver, dynamic relaxation: iterations over which the load is applied, at least "
                        "(default: DynamicRelaxation's)")
    p.add_argument("--volume-cm3", type=positive, default=1000.0, help="mesh, segment: phantom breast volume (cm^3)")
    p.add_argument("--tumour-mm", type=non_negative, default=20.0, help="segment: phantom tumour diameter (0: none)")
    p.add_argument("--snr", type=positive, default=30.0, help="segment: phantom fat signal / noise sigma")
    p.add_argument("--bias", type=non_negative, default=0.2, help="segment: phantom bias field amplitude")
    p.add_argument("--seed", type=non_negative_int, default=1, help="segment: phantom random seed")
    p.add_argument("--edge-mm", type=positive, default=3.0, help="mesh: element edge (mm)")
    p.add_argument("--grid", type=positive_int, nargs=3, metavar=("NX", "NY", "NZ"),
                   help="mesh, segment: pad or crop the phantom to this many voxels (e.g. 256 256 80); warp: the grid")
    p.add_argument("--radii", type=positive, nargs=3, default=[70.0, 60.0, 65.0], metavar=("LR", "AP", "SI"),
                   help="optimise: synthetic breast radii (mm)")
    p.add_argument("--element-mm", type=positive, default=4.0, help="optimise: synthetic mesh cube size (mm)")
    p.add_argument("--voxel-mm", type=positive, nargs=3, default=[1.0, 1.0, 2.5],
                   help="optimise, diagnose: voxel size (mm)")
    p.add_argument("--stair-corners", action="store_true",
                   help="optimise: leave the synthetic mesh's stair corners protruding from its ellipsoid (the "
                        "bench's mesh before 2026-12-01: most of its failed solves were those corners inverting "
                        "under the plates' rounded edges; by default they are moved onto the ellipsoid)")
    p.add_argument("--optimiser", choices=("hybrid", "cmaes", "cmaes-local"), default="cmaes",
                   help="optimise: the optimiser")
    p.add_argument("--budget", type=positive_int, default=500, help="optimise: forward solves; cohort: per fit")
    p.add_argument("--population", type=positive_int, default=None, help="optimise: CMA-ES population (batch size)")
    p.add_argument("--tolerance-mm", type=positive, default=None,
                   help="optimise: forward solves' relaxation tolerance (default 0.01); unloaded: largest node mismatch "
                        "to reach (default 0.02 mm)")
    p.add_argument("--out", help="optimise: a new folder for the fit's log (evaluations.jsonl: every solve's "
                                 "parameters, objective and status; result.json); diagnose: the case's folder (kept, "
                                 "resumed; default a temporary one); demo: its output folder (default a temporary "
                                 "one); cohort: a new folder for the studies; sweep: a JSON-lines file of finished "
                                 "variants (appended, and resumed from)")
    p.add_argument("--case-dirs", nargs="+", default=[], help="cohort: compressed case folders (table1-cases)")
    p.add_argument("--models", nargs="+", choices=MODEL_CHOICES, default=["iso-homo"], help="cohort: models fitted")
    p.add_argument("--modes", nargs="+", choices=("serial", "dask", "processes"), default=["serial", "dask"],
                   help="cohort: how the study runs (the first is the reference)")
    p.add_argument("--workers", type=non_negative_int, nargs="+",
                   help="cohort: the dask mode's local workers (default one per GPU or core); several counts run the "
                        "dask mode once per count (dask-W), e.g. --workers 1 2 on a two-GPU machine")
    p.add_argument("--sweep", action="store_true",
                   help="segment, mesh: the robustness sweep over phantom variants (anatomy options x image quality; "
                        "mesh: truth and segmentation meshed at every --edges size)")
    p.add_argument("--variants", type=positive_int, default=24, help="sweep: how many variants (default 24)")
    p.add_argument("--family", choices=("anatomy", "tumour"), default=None,
                   help="sweep: the variant family (anatomy: every anatomy option x image quality; tumour: lobulated "
                        "and spiculated tumours in dense gland, their signal up to near the gland's; default anatomy)")
    p.add_argument("--processes", type=positive_int, default=1, help="sweep: variants run side by side")
    p.add_argument("--edges", type=positive, nargs="+", help="mesh sweep: element edges in mm (default 3 4 6 8 10 12 15)")
    p.add_argument("--compression", type=fraction, default=None,
                   help="mesh sweep: also compress every mesh between two plates by this fraction of its thickness "
                        "(e.g. 0.4): whether each solve completes and the elements it inverts (on --device)")
    p.add_argument("--json", action="store_true", help="one JSON line of figures")
    p.set_defaults(func=cmd_bench, needs_vtk=lambda args: args.what not in WITHOUT_VTK)
