"""Command line: ``breastbiomech phantom|segment|mesh|simulate|warp|compare|optimise|demo|bench``.

Each sub-command is a thin layer over library functions; results go to files and a short report
on standard output (``--json`` where a machine reads it).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

from BreastBiomechLib import __version__

MODEL_CHOICES = ("iso-homo", "iso-hetero", "aniso-homo", "aniso-hetero")  # optimisation.space.MODELS
OBJECTIVE_CHOICES = ("nmi", "landmarks", "surface", "nmi+landmarks", "nmi+surface")  # optimisation.forward.OBJECTIVES


def _phantom_parameters(args):
    from BreastBiomechLib.phantom import PhantomParameters, table1_case

    params = table1_case(args.case) if args.case else PhantomParameters()
    overrides = {
        "seed": args.seed, "volume_cm3": args.volume_cm3, "density": args.density,
        "tumour_diameter_mm": args.tumour_mm, "snr": args.snr, "bias_strength": args.bias,
        "spacing_mm": tuple(args.spacing) if args.spacing else None,
        "skin_separate": True if args.skin_separate else None,
    }
    values = params.to_dict()
    values.update({k: v for k, v in overrides.items() if v is not None})
    return PhantomParameters.from_dict(values)


def _add_phantom_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--case", type=int, choices=range(1, 6), metavar="1-5",
                   help="start from the preset for case 1-5 of the seed paper's Table 1")
    p.add_argument("--seed", type=int, help="random seed (same seed, same case)")
    p.add_argument("--volume-cm3", type=float, help="breast volume, 400-1500 cm^3")
    p.add_argument("--density", type=float, help="glandular volume fraction, 0.05-0.65")
    p.add_argument("--tumour-mm", type=float, help="tumour diameter in mm (0: none)")
    p.add_argument("--snr", type=float, help="fat signal / noise sigma")
    p.add_argument("--bias", type=float, help="bias field amplitude (0.2 = +-20%%)")
    p.add_argument("--spacing", type=float, nargs=3, metavar=("L", "P", "S"), help="voxel size in mm")
    p.add_argument("--skin-separate", action="store_true", help="keep skin as its own label")


def _truth_model(args):
    """The truth of ``phantom --compressed``: the Table 1 preset of ``--case`` (else the
    default truth), with ``--compression``, ``--axis`` and ``--truth-edge-mm`` applied."""
    from dataclasses import replace

    from BreastBiomechLib.phantom.compressed import TruthModel, table1_truth

    truth = table1_truth(args.case) if args.case else TruthModel()
    compression = truth.compression if args.compression is None else args.compression
    tilt = None if args.plate_tilt is None else [list(args.plate_tilt), [0.0, 0.0]]
    return replace(truth, compression=compression, axis=args.axis, edge_mm=args.truth_edge_mm,  # checked again
                   friction=args.friction, gravity=args.gravity, compression_gravity=args.compression_gravity,
                   chest_wall=args.chest_wall, chest_wall_stiffness=list(args.chest_wall_stiffness),
                   plate_tilt_deg=tilt, skin=None if args.skin is None else list(args.skin))


def cmd_phantom(args) -> int:
    from BreastBiomechLib.phantom import generate_phantom, write_phantom

    truth = _truth_model(args) if args.compressed else None
    if not args.compressed and args.compression is not None:
        raise ValueError("--compression applies to a compressed case: add --compressed")
    effects = {"--friction": args.friction, "--gravity": args.gravity, "--compression-gravity": args.compression_gravity,
               "--plate-tilt": args.plate_tilt, "--chest-wall": args.chest_wall != "fixed" or None,
               "--skin": args.skin}
    given = [name for name, value in effects.items() if value]
    if given and not args.compressed:
        raise ValueError(f"{', '.join(given)} change the truth simulation of a compressed case: add --compressed")
    case = generate_phantom(_phantom_parameters(args))
    paths = write_phantom(case, args.out, overview=not args.no_overview)
    s = case.summary
    print(f"phantom written to {args.out}: {s['breast_volume_cm3']:.0f} cm3 breast, "
          f"density {s['glandular_density']:.1%}, grid {s['size_voxels']} at {s['spacing_mm']} mm, "
          f"{len(case.landmarks)} landmarks, {s['seconds']:.1f} s")
    for role, path in paths.items():
        print(f"  {role:20s} {path}")
    if truth is not None:
        from BreastBiomechLib.phantom.compressed import compress_phantom
        from BreastBiomechLib.phantom.compressed_files import write_compressed

        compressed = compress_phantom(case, truth, device=args.device,
                                      progress=lambda fraction, message: print(f"  [{fraction:4.0%}] {message}",
                                                                                flush=True))
        paths = write_compressed(compressed, args.out, overview=not args.no_overview)
        c = compressed.summary
        forces = ", ".join(f"{name} {force:.2f} N" for name, force in c["plate_forces_N"].items())
        print(f"compressed case written to {Path(args.out) / 'compressed'}: {truth.compression:.1%} {truth.axis}, "
              f"truth mesh {c['truth_tets']} tets ({truth.edge_mm:g} mm), {c['solve_message']}; plate forces "
              f"{forces}; largest displacement {c['max_displacement_mm']:.1f} mm; {c['seconds']:.0f} s")
        for role, path in paths.items():
            print(f"  {role:20s} {path}")
    return 0


def clear_earlier_fit(folder: Path) -> None:
    """Remove the fit an earlier demo run left in ``folder``: the demo remakes its phantom,
    segmentation and mesh on every run, so that fit is stale (resuming it would replay
    evaluations of another mesh). A folder that holds no fit (no settings.json) is refused."""
    import shutil

    if not folder.exists():
        return
    if not (folder / "settings.json").is_file():
        raise FileExistsError(f"{folder} exists and holds no earlier demo fit; choose another --out for the demo")
    print(f"    replacing the earlier run's fit in {folder}")
    shutil.rmtree(folder)


def cmd_demo(args) -> int:
    """The main job on the built-in phantom: phantom and its compressed "measured" scan,
    segmentation from seed points, FE mesh of the segmentation, a simulation with the starting
    materials, the material fit, and a Markdown report (out/demo/report.md)."""
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
    import warp as wp

    from BreastBiomechLib.io.images import read_image
    from BreastBiomechLib.visualisation import save_overview

    wp.init()
    gpu = (args.device or ("cuda" if wp.get_cuda_device_count() else "cpu")).startswith("cuda")
    # on a CPU: coarser voxels (1.5 x 1.5 x 3 mm), a 6 mm truth mesh, and an 8 mm fitting mesh of
    # a smoother surface (3 mm blur) without refinement at the tissue interfaces (tissues by voxel
    # majority): some 30k tets instead of 120k
    truth_mm, fit_mm, budget = (2.0, 4.0, 200) if gpu else (6.0, 8.0, 12)
    spacing = (1.0, 1.0, 2.5) if gpu else (1.5, 1.5, 3.0)
    budget = args.budget or budget
    out = Path(args.out)
    report = {"steps": []}
    started = time.perf_counter()

    def step(text):
        report["steps"].append([text, time.perf_counter()])
        print(text, flush=True)

    print(f"BreastBiomech {__version__} demo -> {out} ({'GPU' if gpu else 'CPU'}: {truth_mm:g} mm truth mesh, "
          f"{fit_mm:g} mm fitting mesh, {budget} forward solves)")
    step(f"1/6 phantom: Table 1 case {DEMO_CASE} preset, {' x '.join(f'{v:g}' for v in spacing)} mm voxels, "
         "SNR 30, +-20 % bias")
    params = table1_case(DEMO_CASE)
    params.spacing_mm = spacing
    case = generate_phantom(params)
    paths = write_phantom(case, out / "case")
    s = case.summary
    print(f"    {s['breast_volume_cm3']:.0f} cm3, density {s['glandular_density']:.1%}; {s['seconds']:.1f} s")

    truth = table1_truth(DEMO_CASE)
    truth.edge_mm = truth_mm
    step(f"2/6 compressed 'measured' scan: truth simulation of {truth.compression:.0%} LR plate compression "
         f"on a {truth_mm:g} mm truth mesh, imaged with its own noise and bias")
    compressed = compress_phantom(case, truth, device=args.device)
    compressed_paths = write_compressed(compressed, out / "case")
    c = compressed.summary
    print(f"    {c['truth_tets']} tets, {c['solve_message']}; largest displacement {c['max_displacement_mm']:.1f} mm")

    step("3/6 segmentation from seed points (EM + MRF + bias field)")
    tumour = case.summary["tissue_volumes_cm3"].get("tumour", 0.0) > 0
    result = segment_tissues(case.image, seed_points(case.labels, "muscle", SEED_COUNTS["muscle"]).positions,
                             seed_points(case.labels, "tumour", SEED_COUNTS["tumour"]).positions if tumour else None)
    dice = dice_per_tissue(result.labels, case.labels)
    seg_paths = write_segmentation(result, out / "segmentation", {"dice_vs_truth": dice})
    print("    Dice vs the ground truth: " + ", ".join(f"{k} {v:.3f}" for k, v in dice.items()))

    step(f"4/6 tetrahedral fitting mesh of the segmentation ({fit_mm:g} mm"
         + (")" if gpu else ", tissues by voxel majority)"))
    mesh = mesh_labels(result.labels, MeshSettings(edge_mm=fit_mm, refine_interfaces=gpu, blur_mm=0.8 if gpu else 3.0),
                       nipple_mm=case.landmarks.position("nipple"))
    mesh_path = write_vtu(out / "mesh" / "mesh.vtu", mesh.mesh)
    m = mesh.summary()
    print(f"    {m['nodes']} nodes, {m['elements']} tets, {m['quality']['failing']['any']['count']} failing the "
          "seed's quality criteria")

    step(f"5/6 material fit (iso-hetero, E per tissue, CMA-ES, {budget} forward solves; the first is the "
         "simulation with the starting materials)")
    def progress(done, total, best, phase):
        print(f"\r    {done}/{total} solves, best NMI {-best:.4f}", end="", flush=True)

    settings = FitSettings(model="iso-hetero", free=("E",), edge_mm=fit_mm, optimiser="cmaes", budget=budget,
                           population=min(6, budget))
    clear_earlier_fit(out / "fit")
    fit = fit_compressed_case(out / "case", out / "fit", settings, mesh_path=mesh_path, device=args.device,
                              progress=progress)
    print()
    errors = fit.landmark_errors["error_mm"]
    print(f"    best NMI {fit.result.best.nmi:.4f}; landmark error {errors['mean']:.2f} ± {errors['sd']:.2f} mm "
          f"(max {errors['max']:.2f}) against a displacement of {fit.landmark_errors['displacement_mm']['mean']:.1f} mm")

    step("6/6 report")
    save_overview(out / "fit" / "predicted_overview.png", read_image(out / "fit" / "predicted.nrrd"), None,
                  compressed.landmarks, title="FE-predicted compressed MR at the fitted parameters; measured landmarks")
    path = _write_demo_report(out, case, compressed, truth, dice, m, fit, report, time.perf_counter() - started,
                              "GPU" if gpu else "CPU")
    print(f"demo finished in {time.perf_counter() - started:.0f} s: report {path}; open {paths['mr']}, "
          f"{compressed_paths['measured']}, {seg_paths['labels']}, {mesh_path} and {out / 'fit' / 'predicted.nrrd'} "
          "in Slicer")
    return 0


DEMO_CASE = 5  # Table 1 case 5: 716 cm3, 19 % compression, isotropic truth (inside the fitted family)


def _write_demo_report(out: Path, case, compressed, truth, dice, mesh_summary, fit, report, seconds, device) -> Path:
    """out/report.md: what each step made, with pictures (paths relative to ``out``)."""
    times = [t for _, t in report["steps"]] + [time.perf_counter()]
    rows = "\n".join(f"| {text} | {times[i + 1] - times[i]:.0f} |" for i, (text, _) in enumerate(report["steps"]))
    e, d = fit.landmark_errors["error_mm"], fit.landmark_errors["displacement_mm"]
    start = fit.result.evaluations[0]
    materials = "\n".join(
        f"| {name} | {values['E'] / 1e3:.1f} | {truth.materials.get(name, {}).get('E', float('nan')) / 1e3:.1f} |"
        for name, values in fit.result.materials.items())
    text = f"""# BreastBiomech demo report

Made by `breastbiomech demo` on the {device} in {seconds:.0f} s. Everything below is in this folder.

| step | seconds |
|---|---|
{rows}

## Phantom and its compressed "measured" scan

Table 1 case {DEMO_CASE}: {case.summary['breast_volume_cm3']:.0f} cm³, glandular density
{case.summary['glandular_density']:.1%}; compressed by {truth.compression:.0%} between LR plates in a truth simulation
({compressed.summary['truth_tets']} tets of {truth.edge_mm:g} mm; {compressed.summary['solve_message']}).

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

Fat's E is the reference (10 kPa). The demo's budget is small (a CPU run); `breastbiomech optimise`
and `breastbiomech study` (docs/optimisation.md, docs/validation.md) fit with hundreds of solves on a GPU.

![FE-predicted](fit/predicted_overview.png)

![convergence](fit/convergence.png)
"""
    path = out / "report.md"
    path.write_text(text)
    return path


_progress_line = {"open": False}  # a progress line waits for its newline on standard error


def _progress(quiet: bool):
    """A progress callback that redraws one line on standard error (silent when ``quiet``)."""
    def report(fraction, message):
        if not quiet:
            print(f"\r  {fraction:4.0%} {message:40s}", end="", file=sys.stderr, flush=True)
            _progress_line["open"] = True
    return report


def _end_progress() -> None:
    if _progress_line["open"]:
        print(file=sys.stderr)
        _progress_line["open"] = False


def _segmentation_settings(args):
    from BreastBiomechLib.segmentation import EMSettings, SegmentationSettings

    return SegmentationSettings(
        em=EMSettings(mrf_strength=args.mrf, bias_order=args.bias_order, max_iterations=args.iterations,
                      tolerance=args.tolerance, partial_volume=not args.no_partial_volume),
        skin_mm=args.skin_mm, keep_skin=args.keep_skin)


def cmd_segment(args) -> int:
    """Segment an MR volume from seed point lists; write the label map, probabilities, bias field
    and a JSON summary."""
    from BreastBiomechLib.io.images import read_image
    from BreastBiomechLib.io.markups import read_markups
    from BreastBiomechLib.io.segmentation import write_segmentation
    from BreastBiomechLib.segmentation import dice_per_tissue, segment_tissues

    image = read_image(args.volume)
    muscle = read_markups(args.seeds_muscle).positions
    tumour = read_markups(args.seeds_tumour).positions if args.seeds_tumour else None
    result = segment_tissues(image, muscle, tumour, _segmentation_settings(args), progress=_progress(args.quiet))
    _end_progress()
    extra = {"inputs": {"volume": str(args.volume), "seeds_muscle": str(args.seeds_muscle),
                        "seeds_tumour": str(args.seeds_tumour) if args.seeds_tumour else None}}
    if args.reference:
        extra["dice_vs_reference"] = dice_per_tissue(result.labels, read_image(args.reference))
    paths = write_segmentation(result, args.out, extra)
    s = result.summary
    volumes = ", ".join(f"{k} {v:.0f}" for k, v in s["tissue_volumes_cm3"].items())
    print(f"segmentation written to {args.out}: tissue volumes (cm3) {volumes}; "
          f"density {s['glandular_density']:.1%}; {sum(s['seconds'].values()):.1f} s")
    em = s["em"]
    print(f"  EM: {em['iterations']} iterations ({'converged' if em['converged'] else 'NOT converged'}), "
          f"fat {em['class_means']['fat']:.0f}, glandular {em['class_means']['glandular']:.0f}, "
          f"bias field {em['bias_range'][0]:.2f}-{em['bias_range'][1]:.2f}")
    if "dice_vs_reference" in extra:
        print("  Dice vs the reference: " + ", ".join(f"{k} {v:.3f}" for k, v in extra["dice_vs_reference"].items()))
    for role, path in paths.items():
        print(f"  {role:22s} {path}")
    return 0


def cmd_mesh(args) -> int:
    """Mesh a label map; write the mesh, its surfaces, a report, a compression case and its
    NiftySim model."""
    from BreastBiomechLib.io.cases import case_from_dict, compression_case
    from BreastBiomechLib.io.images import read_image
    from BreastBiomechLib.io.markups import read_markups
    from BreastBiomechLib.io.meshes import write_surface, write_vtu
    from BreastBiomechLib.io.niftysim import write_niftysim
    from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels

    labels = read_image(args.labels)
    nipple = None
    if args.landmarks:
        marks = read_markups(args.landmarks)
        if "nipple" not in marks.labels:
            raise ValueError(f"{args.landmarks}: no landmark labelled 'nipple'")
        nipple = marks.positions[marks.labels.index("nipple")]
    settings = MeshSettings(edge_mm=args.edge_mm, interface_edge_mm=args.interface_edge_mm,
                            refine_interfaces=not args.no_refine)

    result = mesh_labels(labels, settings, nipple_mm=nipple, progress=_progress(args.quiet))
    _end_progress()
    out = Path(args.out)
    paths = {"mesh": write_vtu(out / "mesh.vtu", result.mesh)}
    for name, surface in result.surfaces.items():
        paths[f"surface_{name}"] = write_surface(out / "surfaces" / f"{name}.vtp", surface)
    summary = result.summary()
    case = compression_case(result.mesh, "mesh.vtu", args.axis, args.compression,
                            chest_clearance_mm=args.chest_clearance_mm)
    paths["case"] = out / "case.json"
    paths["case"].write_text(json.dumps(case, indent=1) + "\n")
    model, _ = case_from_dict(case, result.mesh, paths["case"])
    paths["niftysim"] = write_niftysim(out / "model.xml", model, drop_settling=True)
    paths["report"] = out / "mesh_report.json"
    paths["report"].write_text(json.dumps(summary, indent=1) + "\n")
    failing = summary["quality"]["failing"]["any"]
    print(f"mesh written to {out}: {summary['nodes']} nodes, {summary['elements']} tets, "
          f"{summary['volume_cm3']:.0f} cm3, {summary['seconds']['total']:.1f} s")
    print("  elements per tissue: " + ", ".join(f"{k} {v}" for k, v in summary["elements_per_tissue"].items()))
    print(f"  quality: {failing['count']} elements ({failing['percent']:.3f} %) fail the seed's criteria; "
          f"smallest dihedral angle {summary['quality']['dihedral_min_deg']:.1f} deg")
    print("  tissue Dice vs the label map: " + ", ".join(
        f"{k} {v['dice']:.3f}" for k, v in summary["tissue_representation"].items()))
    for note in summary["notes"]:
        print(f"  note: {note}")
    for role, path in paths.items():
        print(f"  {role:20s} {path}")
    return 0


def cmd_simulate(args) -> int:
    """Solve CASE.json; write the mesh with its displacement and a JSON summary of the solve."""
    import numpy as np

    from BreastBiomechLib.io.cases import read_case
    from BreastBiomechLib.io.meshes import write_vtu
    from BreastBiomechLib.mesh.tetmesh import TetMesh
    from BreastBiomechLib.solver import solve
    from BreastBiomechLib.solver.static import solve_static

    model, settings = read_case(args.case)
    device = args.device or settings.device
    relaxation = settings.relaxation if settings.method == "relaxation" else None
    mesh = model.mesh
    print(f"simulate {args.case}: {len(mesh.nodes)} nodes, {len(mesh.tets)} tets, {model.formulation}, "
          f"{settings.method}, device {device or 'default'}")

    def report(fraction):
        print(f"\r  {fraction:6.1%} of the step budget", end="", file=sys.stderr, flush=True)

    reference_state = None
    if settings.unloaded is not None:
        from BreastBiomechLib.solver.unloaded import start_from_reference_state

        model, reference_state = start_from_reference_state(
            model, settings.unloaded, device, progress=None if args.quiet else lambda i, r: print(
                f"  unloaded shape: iteration {i}, largest node mismatch {r:.4f} mm", file=sys.stderr))
        print(f"  unloaded reference state: {reference_state['iterations']} iterations, residual "
              f"{reference_state['residual_mm']:.3g} mm, largest gravity sag {reference_state['largest_sag_mm']:.2f} mm, "
              f"{reference_state['wall_s']:.1f} s")
    if settings.method == "static":
        solution = solve_static(model, increments=settings.increments)
    else:
        solution = solve(model, device=device, relaxation=relaxation, progress=None if args.quiet else report,
                         steady_state_mm=settings.steady_state_mm, mass_scaling=settings.mass_scaling)
    if not args.quiet:
        print(file=sys.stderr)
    out = Path(args.out)
    # displacements from the mesh as given (the imaged shape, also with a pre-stressed start)
    from BreastBiomechLib.solver.unloaded import displacement_from_imaged

    point_data = {**mesh.point_data, "displacement": displacement_from_imaged(model, solution.displacement, mesh.nodes)}
    if reference_state is not None:
        point_data["unloaded_displacement"] = model.mesh.nodes - mesh.nodes
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
    (out / "solution.json").write_text(json.dumps(summary, indent=1, allow_nan=True))
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


def _nodal_displacement(path: str, mesh) -> "np.ndarray":
    """Nodal displacements (N, 3) mm from a .vtu with a ``displacement`` point array (e.g.
    ``simulate``'s deformed.vtu) or a .npy array, checked against ``mesh``."""
    import numpy as np

    from BreastBiomechLib.io.meshes import read_vtu

    if str(path).endswith(".npy"):
        displacement = np.load(path)
    else:
        other = read_vtu(path)
        if "displacement" not in other.point_data:
            raise ValueError(f"{path}: no 'displacement' point array (simulate's deformed.vtu has one)")
        displacement = other.point_data["displacement"]
    if displacement.shape != mesh.nodes.shape:
        raise ValueError(f"{path}: {displacement.shape[0]} displacement vectors for a mesh of {len(mesh.nodes)} nodes; "
                         "the displacement must come from a solve of this mesh")
    return displacement


def cmd_warp(args) -> int:
    """The FE-predicted deformed image (and optionally the displacement field and the moved
    landmarks) of a displacement of a mesh."""
    import numpy as np
    import SimpleITK as sitk

    from BreastBiomechLib.io.images import read_image, write_image
    from BreastBiomechLib.io.markups import read_markups, write_markups
    from BreastBiomechLib.io.meshes import read_vtu
    from BreastBiomechLib.landmarks import map_landmarks
    from BreastBiomechLib.warping import ImageWarper

    mesh = read_vtu(args.mesh)
    displacement = _nodal_displacement(args.displacement, mesh)
    volume = read_image(args.volume)
    like = read_image(args.like) if args.like else volume
    started = time.perf_counter()
    warper = ImageWarper(mesh, volume, like, device=args.device, background=args.background)
    predicted = warper.predict(displacement)
    wall = time.perf_counter() - started
    written = [write_image(args.out, predicted.image)]
    if args.inside:
        written.append(write_image(args.inside, predicted.inside))
    if args.field:
        written.append(write_image(args.field, warper.displacement_field(displacement)))
    if args.landmarks:
        if not args.landmarks_out:
            raise ValueError("--landmarks needs --landmarks-out (where to write the moved landmarks)")
        moved = map_landmarks(mesh, displacement, read_markups(args.landmarks))
        written.append(write_markups(args.landmarks_out, moved, name="Predicted landmarks"))
    inside = int(np.count_nonzero(sitk.GetArrayViewFromImage(predicted.inside)))
    print(f"predicted image on a {'x'.join(map(str, like.GetSize()))} grid: {inside} voxels inside the deformed "
          f"mesh; {wall:.2f} s on {warper.device}")
    for path in written:
        print(f"  {path}")
    return 0


def cmd_compare(args) -> int:
    """NMI and NCC of a predicted and a measured image, and landmark errors."""
    import numpy as np

    from BreastBiomechLib.io.images import read_image
    from BreastBiomechLib.io.markups import read_markups
    from BreastBiomechLib.landmarks import landmark_errors
    from BreastBiomechLib.similarity import Similarity

    predicted, measured = read_image(args.predicted), read_image(args.measured)
    if predicted.GetSize() != measured.GetSize() or not np.allclose(predicted.GetOrigin(), measured.GetOrigin(), atol=1e-3):
        raise ValueError("the predicted and measured images are on different grids; warp with --like MEASURED")
    mask = read_image(args.mask) if args.mask else None
    measure = Similarity(measured, mask, bins=args.bins, device=args.device)
    figures = {"nmi": measure.nmi(predicted), "ncc": measure.ncc(predicted), "bins": args.bins,
               "masked_voxels": int(measure.joint_histogram(predicted).sum())}
    if args.landmarks:
        reference, moved, truth = (read_markups(p) for p in args.landmarks)
        errors = landmark_errors(reference, moved, truth)
        figures["landmarks"] = {**errors.summary(), "per_landmark": {
            label: {"displacement_mm": float(d), "error_mm": float(e)}
            for label, d, e in zip(errors.labels, errors.displacement_mm, errors.error_mm)}}
    if args.json:
        print(json.dumps(figures))
        return 0
    print(f"NMI {figures['nmi']:.4f} ({args.bins} bins, {figures['masked_voxels']} voxels), NCC {figures['ncc']:.4f}")
    if args.landmarks:
        print(f"{'landmark':10s} {'displacement (mm)':>18s} {'error (mm)':>11s}")
        for label, row in figures["landmarks"]["per_landmark"].items():
            print(f"{label:10s} {row['displacement_mm']:18.2f} {row['error_mm']:11.2f}")
        s = figures["landmarks"]
        print(f"{'mean ± sd':10s} {s['displacement_mm']['mean']:11.2f} ± {s['displacement_mm']['sd']:4.2f} "
              f"{s['error_mm']['mean']:6.2f} ± {s['error_mm']['sd']:.2f}")
        print(f"{'max':10s} {s['displacement_mm']['max']:18.2f} {s['error_mm']['max']:11.2f}")
    return 0


def cmd_optimise(args) -> int:
    """Fit material parameters to a compressed case (seed section 2.4)."""
    from BreastBiomechLib.optimisation.case import FitSettings, fit_compressed_case

    settings = FitSettings(model=args.model, free=tuple(args.free), fibre=tuple(args.fibre), edge_mm=args.edge_mm,
                           optimiser=args.optimiser, budget=args.budget, seconds=args.seconds, seed=args.seed,
                           objective=args.objective, bins=args.bins, tolerance_mm=args.tolerance_mm,
                           population=args.population)
    started = time.perf_counter()

    def progress(done, budget, best, phase):
        if not args.quiet:
            width = 30
            filled = int(width * done / budget)
            print(f"\r  [{'#' * filled}{'.' * (width - filled)}] {done}/{budget} {phase:6s} best {best:.5f} "
                  f"{time.perf_counter() - started:6.0f} s", end="", file=sys.stderr, flush=True)

    fit = fit_compressed_case(args.case_dir, args.out, settings, labels=args.labels, mesh_path=args.mesh,
                              resume=args.resume, device=args.device, progress=progress)
    if not args.quiet:
        print(file=sys.stderr)
    summary = fit.result.summary()
    if args.json:
        print(json.dumps({**summary, "landmark_errors": fit.landmark_errors}))
        return 0
    best = fit.result.best
    print(f"{settings.model} fit of {args.case_dir} ({settings.optimiser}, {summary['evaluations']} evaluations, "
          f"{summary['replayed']} replayed, stopped: {summary['stopped']}, {summary['seconds']:.0f} s)")
    print(f"  best objective {best.objective:.5f}: NMI {best.nmi:.4f}, NCC {best.ncc:.4f}")
    for name, values in fit.result.materials.items():
        print(f"  {name:10s} E {values['E']:10.0f} Pa  nu {values['nu']:.4f}  eta {values['eta']:10.1f} Pa")
    if "fibre" in fit.result.geometry:
        print("  fibre direction (LPS) " + " ".join(f"{v:.3f}" for v in fit.result.geometry["fibre"]))
    if "plate_offsets_mm" in fit.result.geometry:
        print("  plate offsets (mm, towards the tissue) " + " ".join(f"{v:.2f}" for v in fit.result.geometry["plate_offsets_mm"]))
    if fit.landmark_errors:
        e = fit.landmark_errors
        print(f"  landmarks: displacement {e['displacement_mm']['mean']:.2f} ± {e['displacement_mm']['sd']:.2f} mm, "
              f"error {e['error_mm']['mean']:.2f} ± {e['error_mm']['sd']:.2f} mm (max {e['error_mm']['max']:.2f})")
    print(f"  results in {fit.folder}")
    return 0


BENCH_RADII_MM = (80.0, 70.0, 75.0)  # the benchmarks' hemi-ellipsoid (hemi_ellipsoid_compression's default)


def _hemi_ellipsoid_spacing(tets: int) -> float:
    """The grid spacing (mm) that gives the benchmarks' hemi-ellipsoid about ``tets`` elements."""
    import numpy as np

    return float((np.pi * 4 * np.prod(BENCH_RADII_MM) / tets) ** (1 / 3))


def _bench_solver(args) -> dict:
    """One forward solve (or a batch) of the hemi-ellipsoid compression case; figures as a dict."""
    import numpy as np
    import warp as wp

    from BreastBiomechLib.solver import DynamicRelaxation, solve_batch
    from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression

    spacing = _hemi_ellipsoid_spacing(args.tets)
    settle = 0.25 * args.total_time if args.settle_time is None else args.settle_time
    model = hemi_ellipsoid_compression(spacing, compression=0.25, total_time=args.total_time, settle_time=settle)
    for plate in model.loading.plates:
        plate.friction = args.friction
    wp.init()
    device = wp.get_device(args.device)
    rng = np.random.default_rng(0)
    base = model.materials
    variants = [base] + [type(base)(base.mu * f, base.kappa * f, base.eta, base.fibre, base.density)
                         for f in rng.uniform(0.7, 1.3, args.batch - 1)]
    warm = hemi_ellipsoid_compression(20.0, total_time=0.05, settle_time=0.0)
    solve_batch(warm, [warm.materials], device=device)  # compile the kernels once, outside the timing
    started = time.perf_counter()
    load = {} if args.load_iterations is None else {"load_iterations": args.load_iterations}
    relaxation = DynamicRelaxation(tolerance_mm=0.01, **load) if args.relaxation else None
    solutions = solve_batch(model, variants, device=device, relaxation=relaxation,
                            steady_state_mm=args.steady_state_mm)
    wall = time.perf_counter() - started
    s = solutions[0]
    memory_mb = None
    if device.is_cuda:  # device memory in use after the solve (warp's pool included)
        memory_mb = round((device.total_memory - device.free_memory) / 2**20, 1)
    n, m = len(model.mesh.nodes), len(model.mesh.tets)
    bytes_per_step = args.batch * (324 * m + 70 * n)  # reads/writes/atomics per step, see docs
    return {
        "benchmark": "solver", "device": str(device), "device_name": getattr(device, "name", ""),
        "nodes": n, "tets": m, "batch": args.batch, "formulation": model.formulation, "friction": args.friction,
        "method": "dynamic relaxation" if args.relaxation else "physical time",
        "load_iterations": relaxation.load_iterations if relaxation else None,
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
    }


def _bench_unloaded(args) -> dict:
    """The unloaded reference state of the hemi-ellipsoid breast of about ``--tets`` tets imaged
    prone (gravity 9.81 m/s^2 anterior) with the seed's chest wall: iterations, residual, wall
    time and the gravity sag."""
    import warp as wp

    from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression
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
    from dataclasses import replace

    import numpy as np

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
    import os

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
    import numpy as np
    import SimpleITK as sitk
    import warp as wp

    from BreastBiomechLib.mesh.primitives import hemi_ellipsoid_mesh
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
    import os

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


def _bench_optimise(args) -> dict:
    """An end-to-end aniso-hetero fit (4 tissues x E, nu, eta; fat's E the reference) of the
    synthetic breast (optimisation.synthetic: ``--radii``, ``--element-mm``, ``--voxel-mm``)
    whose measured image is the prediction at :data:`BENCH_TRUTH`, within ``--budget`` solves
    by ``--optimiser``; the case's set-up is not timed."""
    import numpy as np

    from BreastBiomechLib.optimisation import FittingProblem, ParameterSpace, optimise
    from BreastBiomechLib.optimisation.synthetic import measured_at, synthetic_case
    from BreastBiomechLib.solver import DynamicRelaxation

    case = synthetic_case(tuple(args.radii), element_mm=args.element_mm, voxel_mm=tuple(args.voxel_mm),
                          muscle_mm=10.0, tumour_mm=0.3 * args.radii[0])
    space = ParameterSpace.for_model("aniso-hetero", ["fat", "glandular", "muscle", "tumour"])
    relaxation = DynamicRelaxation(tolerance_mm=0.01 if args.tolerance_mm is None else args.tolerance_mm)
    measured = measured_at(case, space, BENCH_TRUTH, relaxation, device=args.device)
    problem = FittingProblem(space, case.mesh, case.undeformed, measured, case.planes, relaxation=relaxation,
                             device=args.device)
    started = time.perf_counter()
    result = optimise(problem, args.optimiser, budget=args.budget, seed=args.seed, out_dir=args.out,
                      population=args.population)
    seconds = time.perf_counter() - started
    truth = problem.evaluate(space.unit(BENCH_TRUTH))[0]
    errors = {key: round(abs(value / BENCH_TRUTH[key] - 1.0), 4) for key, value in result.best.values.items()}
    best_so_far = np.maximum.accumulate([e.nmi if e.status == "completed" else 0.0 for e in result.evaluations])
    quarters = sorted({max(1, round(q * len(best_so_far))) for q in (0.25, 0.5, 0.75, 1.0)})
    return {"benchmark": "optimise", "version": __version__, "device": str(problem.warper.device),
            "optimiser": args.optimiser, "tets": len(case.mesh.tets), "nodes": len(case.mesh.nodes),
            "voxels": int(measured.GetNumberOfPixels()), "free_parameters": space.dimension,
            "budget": args.budget, "evaluations": len(result.evaluations), "stopped": result.stopped,
            "failed": sum(e.status != "completed" for e in result.evaluations),
            "seconds": round(seconds, 2), "seconds_per_evaluation": round(seconds / len(result.evaluations), 4),
            "best_nmi": round(result.best.nmi, 5), "truth_nmi": round(truth.nmi, 5),
            "best_nmi_after": {str(n): round(float(best_so_far[n - 1]), 5) for n in quarters},
            "max_relative_error": max(errors.values()), "relative_errors": errors}


def cmd_study(args) -> int:
    """The four-model study of the seed's Tables 2 and 3 on compressed cases."""
    import datetime

    from BreastBiomechLib.optimisation.study import (StudySettings, provenance, run_study, study_markdown,
                                                     write_report)

    budgets = {}
    for item in args.budget or []:
        model, _, count = item.partition("=")
        if model not in MODEL_CHOICES or not count.isdigit():
            raise ValueError(f"--budget takes MODEL=SOLVES with MODEL one of {MODEL_CHOICES}, not {item!r}")
        budgets[model] = int(count)
    settings = StudySettings(models=tuple(args.models), optimisers=tuple(args.optimisers),
                             budgets={**StudySettings().budgets, **budgets}, fibre=tuple(args.fibre),
                             edge_mm=args.edge_mm, seed=args.seed, bins=args.bins, tolerance_mm=args.tolerance_mm)
    started = time.perf_counter()

    def progress(fit, done, budget, best, phase):
        if not args.quiet:
            print(f"\r  {fit}: {done}/{budget} {phase:6s} best {best:.5f} {time.perf_counter() - started:6.0f} s ",
                  end="", file=sys.stderr, flush=True)

    rows = run_study(args.case_dirs, args.out, settings, device=args.device, progress=progress)
    if not args.quiet:
        print(file=sys.stderr)
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
    return 0


def cmd_bench(args) -> int:
    if args.what == "solver":
        figures = _bench_solver(args)
        if args.json:
            print(json.dumps(figures))
        else:
            for key, value in figures.items():
                print(f"{key:32s} {value}")
        return 0
    if args.what in ("mesh", "segment", "warp", "optimise", "unloaded", "effects"):
        figures = {"mesh": _bench_mesh, "segment": _bench_segment, "warp": _bench_warp,
                   "optimise": _bench_optimise, "unloaded": _bench_unloaded, "effects": _bench_effects}[args.what](args)
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


def _non_negative(text: str) -> float:
    """An argparse type: a finite number >= 0."""
    value = float(text)
    if not (value >= 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, not {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="breastbiomech", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("phantom", help="generate a synthetic breast MR case with ground truth")
    p.add_argument("--out", required=True, help="output folder")
    _add_phantom_options(p)
    p.add_argument("--no-overview", action="store_true", help="skip the PNG overview")
    p.add_argument("--compressed", action="store_true",
                   help="also write a compressed 'measured' case (OUT/compressed): a truth simulation with hidden "
                        "materials, imaged like a second scan, its landmarks and plates")
    p.add_argument("--compression", type=float,
                   help="fraction of the breast's thickness the plates close (default: the seed's for --case, else 0.25)")
    p.add_argument("--axis", choices=("LR", "SI"), default="LR", help="compression axis (default LR, as the seed)")
    p.add_argument("--truth-edge-mm", type=float, default=2.0,
                   help="element size of the truth mesh (default 2 mm: finer than any fitting mesh)")
    p.add_argument("--device", help="warp device of the truth simulation (cuda, cpu; default: warp's)")
    effects = p.add_argument_group("hidden effects of the truth simulation (recorded in truth.json only)")
    effects.add_argument("--friction", type=_non_negative, default=0.0, help="the plates' Coulomb friction mu")
    effects.add_argument("--gravity", type=float, nargs=3, metavar=("GX", "GY", "GZ"),
                         help="gravity the scan was imaged under (m/s^2, LPS; prone: 0 -9.81 0): the truth starts "
                              "pre-stressed from its unloaded state")
    effects.add_argument("--compression-gravity", type=float, nargs=3, metavar=("GX", "GY", "GZ"),
                         help="gravity while the plates close (default: --gravity's)")
    effects.add_argument("--chest-wall", choices=("fixed", "sliding", "elastic"), default="fixed",
                         help="the chest wall's support (default fixed, as the seed)")
    effects.add_argument("--chest-wall-stiffness", type=_non_negative, nargs=2, default=[0.0, 0.0],
                         metavar=("NORMAL", "TANGENTIAL"), help="elastic or sliding chest wall's springs (Pa/mm)")
    effects.add_argument("--skin", type=float, nargs=2, metavar=("E_PA", "THICKNESS_MM"),
                         help="a skin layer of this Young's modulus and thickness (partial-volume weighting)")
    effects.add_argument("--plate-tilt", type=float, nargs=2, metavar=("DEG1", "DEG2"),
                         help="the first plate's tilt about its two tilt axes (degrees, at most 10)")
    p.set_defaults(func=cmd_phantom)

    p = sub.add_parser("optimise", help="fit tissue material parameters to a compressed case by maximising NMI")
    p.add_argument("case_dir", help="a case folder with its compressed/ part (`breastbiomech phantom --compressed`)")
    p.add_argument("--out", required=True, help="output folder (results written as the fit goes)")
    p.add_argument("--model", choices=MODEL_CHOICES, default="aniso-hetero", help="the seed's model variant")
    p.add_argument("--free", nargs="+", choices=("E", "nu", "eta", "fibre", "offset"), default=["E", "nu", "eta"],
                   help="parameters searched per material (fat's E is the reference, eta only for aniso models); "
                        "fibre: the fibre direction's angles (aniso models); offset: each plate's position")
    p.add_argument("--fibre", type=float, nargs=3, default=[0.0, 0.0, 1.0], metavar=("X", "Y", "Z"),
                   help="fibre direction of the anisotropic models (LPS unit vector; default SI)")
    p.add_argument("--optimiser", choices=("hybrid", "cmaes"), default="hybrid",
                   help="hybrid: annealing then L-BFGS-B (the seed's); cmaes: CMA-ES, one batch per generation")
    p.add_argument("--budget", type=int, default=500, help="forward solves in all (default 500)")
    p.add_argument("--seconds", type=float, help="wall-time limit of this run (s)")
    p.add_argument("--seed", type=int, default=0, help="random seed (same seed, same run)")
    p.add_argument("--population", type=int, help="CMA-ES population per generation (default 4 + 3 ln d)")
    p.add_argument("--objective", choices=OBJECTIVE_CHOICES, default="nmi",
                   help="nmi (the seed's), landmarks (mean error), surface (mean distance of the predicted breast "
                        "skin to the measured body surface) or a weighted sum with NMI (default nmi)")
    p.add_argument("--bins", type=int, default=64, help="NMI histogram bins (default 64)")
    p.add_argument("--mesh", help="fitting mesh (.vtu from `breastbiomech mesh`); default: made from the labels")
    p.add_argument("--labels", help="label map to mesh (default: the case's labels.nrrd)")
    p.add_argument("--edge-mm", type=float, default=4.0, help="fitting mesh element size (default 4 mm)")
    p.add_argument("--tolerance-mm", type=float, default=0.01, help="forward solves' relaxation tolerance (mm)")
    p.add_argument("--device", help="warp device (cuda, cpu; default: warp's)")
    p.add_argument("--resume", action="store_true", help="continue a fit interrupted in --out")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_optimise)

    p = sub.add_parser("study", help="the four model variants fitted to compressed cases (the seed's Tables 2, 3)")
    p.add_argument("case_dirs", nargs="+", help="compressed case folders (`make table1-cases`: out/table1/case*)")
    p.add_argument("--out", required=True, help="results folder (rerun to resume)")
    p.add_argument("--models", nargs="+", choices=MODEL_CHOICES, default=list(MODEL_CHOICES))
    p.add_argument("--optimisers", nargs="+", choices=("hybrid", "cmaes"), default=["cmaes"])
    p.add_argument("--budget", nargs="+", metavar="MODEL=SOLVES",
                   help="forward solves per fit of a model (default iso-homo=24 aniso-homo=48 iso-hetero=160 "
                        "aniso-hetero=240)")
    p.add_argument("--fibre", type=float, nargs=3, default=[0.0, 0.0, 1.0], metavar=("X", "Y", "Z"),
                   help="fibre direction of the anisotropic models (LPS unit vector; default SI)")
    p.add_argument("--edge-mm", type=float, default=4.0, help="fitting mesh element size (default 4 mm)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--bins", type=int, default=64, help="NMI histogram bins (default 64)")
    p.add_argument("--tolerance-mm", type=float, default=0.01, help="forward solves' relaxation tolerance (mm)")
    p.add_argument("--device", help="warp device (cuda, cpu; default: warp's)")
    p.add_argument("--report", help="Markdown file whose study tables are (re)written, e.g. docs/validation.md")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.set_defaults(func=cmd_study)

    p = sub.add_parser("segment", help="tissue label map and probabilities of an MR volume (EM + MRF + bias, seeds)")
    p.add_argument("volume", help="MR volume (.nrrd/.nii.gz), T1-weighted without fat suppression")
    p.add_argument("--seeds-muscle", required=True, help="point list (.mrk.json) on the pectoral muscle, 3-5 spread over it")
    p.add_argument("--seeds-tumour", help="point list (.mrk.json) inside the tumour, if there is one")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--mrf", type=float, default=0.4, help="MRF strength beta (0: no spatial prior; default 0.4)")
    p.add_argument("--bias-order", type=int, default=3, help="bias-field polynomial order (0: none; default 3)")
    p.add_argument("--iterations", type=int, default=40, help="EM iterations at most (default 40)")
    p.add_argument("--tolerance", type=float, default=1e-5, help="EM stop: relative log-likelihood change (default 1e-5)")
    p.add_argument("--no-partial-volume", action="store_true", help="two pure classes only (no mixed-voxel class)")
    p.add_argument("--skin-mm", type=float, default=3.0, help="outer breast layer labelled skin (default 3 mm)")
    p.add_argument("--keep-skin", action="store_true", help="label skin separately (default: folded into fat)")
    p.add_argument("--reference", help="ground-truth label map: report Dice per tissue")
    p.add_argument("--quiet", action="store_true", help="no progress on standard error")
    p.set_defaults(func=cmd_segment)

    p = sub.add_parser("mesh", help="tetrahedral FE mesh of a tissue label map (TetGen), with a compression case")
    p.add_argument("labels", help="label map (.nrrd/.nii.gz) with the label table's values")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--edge-mm", type=float, default=3.0, help="element edge length in mm (default 3)")
    p.add_argument("--interface-edge-mm", type=float, default=None,
                   help="spacing of the points inserted on tissue interfaces (default: --edge-mm)")
    p.add_argument("--no-refine", action="store_true", help="do not insert tissue-interface points")
    p.add_argument("--landmarks", help="a .mrk.json with a point labelled 'nipple' (the nipple node)")
    p.add_argument("--axis", default="LR", choices=["LR", "AP", "SI"], help="compression axis of case.json")
    p.add_argument("--compression", type=float, default=0.25, help="compression of case.json, fraction of thickness")
    p.add_argument("--chest-clearance-mm", type=float, default=None,
                   help="band anterior to the chest wall the plates do not touch (default: the plate travel, >= 5 mm)")
    p.add_argument("--quiet", action="store_true", help="no progress on standard error")
    p.set_defaults(func=cmd_mesh)

    p = sub.add_parser("simulate", help="solve a case file (mesh + materials + loading, see docs/solver.md)")
    p.add_argument("case", help="CASE.json")
    p.add_argument("--out", required=True, help="output folder for deformed.vtu and solution.json")
    p.add_argument("--device", default=None, help="cuda, cpu or a warp device name (default: the case's, or warp's)")
    p.add_argument("--quiet", action="store_true", help="no progress on standard error")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("warp", help="FE-predicted deformed image of a volume through a mesh displacement")
    p.add_argument("mesh", help="reference mesh (.vtu)")
    p.add_argument("displacement", help="nodal displacements: a .vtu with a 'displacement' point array "
                                        "(simulate's deformed.vtu) or a .npy (N, 3) array, mm")
    p.add_argument("volume", help="the undeformed image to warp (.nrrd/.nii.gz)")
    p.add_argument("--like", help="image whose grid the prediction takes (the measured deformed image; default VOLUME's)")
    p.add_argument("--out", required=True, help="predicted image file")
    p.add_argument("--inside", help="also write the mask of voxels inside the deformed mesh here")
    p.add_argument("--field", help="also write the dense displacement field (ITK convention) here")
    p.add_argument("--landmarks", help="reference landmarks (.mrk.json) to move with the displacement")
    p.add_argument("--landmarks-out", help="where to write the moved landmarks (.mrk.json)")
    p.add_argument("--background", type=float, default=0.0, help="value outside the deformed body (default 0)")
    p.add_argument("--device", default=None, help="cuda, cpu or a warp device name (default: warp's)")
    p.set_defaults(func=cmd_warp)

    p = sub.add_parser("compare", help="NMI and NCC of predicted vs measured image, and landmark errors")
    p.add_argument("predicted", help="predicted image (from warp)")
    p.add_argument("measured", help="measured image on the same grid")
    p.add_argument("--mask", help="compare only the non-zero voxels of this image (e.g. warp --inside)")
    p.add_argument("--bins", type=int, default=64, help="histogram bins per image for NMI (default 64)")
    p.add_argument("--landmarks", nargs=3, metavar=("REFERENCE", "PREDICTED", "MEASURED"),
                   help="three .mrk.json point lists matched by label: errors as in the seed's Table 2")
    p.add_argument("--device", default=None, help="cuda, cpu or a warp device name (default: warp's)")
    p.add_argument("--json", action="store_true", help="one JSON line of figures")
    p.set_defaults(func=cmd_compare)

    p = sub.add_parser("demo", help="run the main job on the built-in phantom")
    p.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    p.add_argument("--device", help="warp device (default: the GPU when there is one)")
    p.add_argument("--budget", type=int, help="forward solves of the fit (default 12 on a CPU, 200 on a GPU)")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("bench", help="print benchmark figures")
    p.add_argument("what", choices=["phantom", "segment", "mesh", "solver", "unloaded", "effects", "warp", "optimise"],
                   help="what to time")
    p.add_argument("--cases", type=int, nargs="+", default=[1, 2, 3, 4, 5],
                   help="Table 1 cases (phantom; effects: the first)")
    p.add_argument("--truth-edge-mm", type=float, default=3.0, help="effects: the truth mesh's element size (mm)")
    p.add_argument("--tets", type=int, default=160_000, help="solver, warp: about this many tets (hemi-ellipsoid)")
    p.add_argument("--repeat", type=int, default=10, help="warp: timed calls (median and best reported)")
    p.add_argument("--batch", type=int, default=1, help="solver: parameter sets solved in one launch")
    p.add_argument("--device", default=None, help="solver, warp: cuda, cpu or a warp device name (default: warp's)")
    p.add_argument("--total-time", type=float, default=1.0, help="solver: loading time in s (+25%% settling)")
    p.add_argument("--settle-time", type=float, default=None, help="solver: settling time in s (default 25%% of loading)")
    p.add_argument("--steady-state-mm", type=float, default=None,
                   help="solver, physical time: stop settling once this close to rest (mm)")
    p.add_argument("--relaxation", action="store_true", help="solver: dynamic relaxation (tolerance 0.01 mm)")
    p.add_argument("--friction", type=_non_negative, default=0.0, help="solver: the plates' Coulomb friction mu")
    p.add_argument("--load-iterations", type=int, default=None,
                   help="solver, dynamic relaxation: iterations over which the load is applied, at least "
                        "(default: DynamicRelaxation's)")
    p.add_argument("--volume-cm3", type=float, default=1000.0, help="mesh, segment: phantom breast volume (cm^3)")
    p.add_argument("--tumour-mm", type=float, default=20.0, help="segment: phantom tumour diameter (0: none)")
    p.add_argument("--snr", type=float, default=30.0, help="segment: phantom fat signal / noise sigma")
    p.add_argument("--bias", type=float, default=0.2, help="segment: phantom bias field amplitude")
    p.add_argument("--seed", type=int, default=1, help="segment: phantom random seed")
    p.add_argument("--edge-mm", type=float, default=3.0, help="mesh: element edge (mm)")
    p.add_argument("--grid", type=int, nargs=3, metavar=("NX", "NY", "NZ"),
                   help="mesh, segment: pad or crop the phantom to this many voxels (e.g. 256 256 80); warp: the grid")
    p.add_argument("--radii", type=float, nargs=3, default=[70.0, 60.0, 65.0], metavar=("LR", "AP", "SI"),
                   help="optimise: synthetic breast radii (mm)")
    p.add_argument("--element-mm", type=float, default=4.0, help="optimise: synthetic mesh cube size (mm)")
    p.add_argument("--voxel-mm", type=float, nargs=3, default=[1.0, 1.0, 2.5], help="optimise: voxel size (mm)")
    p.add_argument("--optimiser", choices=("hybrid", "cmaes"), default="cmaes", help="optimise: the optimiser")
    p.add_argument("--budget", type=int, default=500, help="optimise: forward solves")
    p.add_argument("--population", type=int, default=None, help="optimise: CMA-ES population (batch size)")
    p.add_argument("--tolerance-mm", type=float, default=None,
                   help="optimise: forward solves' relaxation tolerance (default 0.01); unloaded: largest node mismatch "
                        "to reach (default 0.02 mm)")
    p.add_argument("--out", help="optimise: a new folder for the fit's log (evaluations.jsonl: every solve's "
                                 "parameters, objective and status; result.json)")
    p.add_argument("--json", action="store_true", help="one JSON line of figures")
    p.set_defaults(func=cmd_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # as typed, for reports' provenance
    if getattr(args, "json", False):  # standard output is for the one JSON line: no warp banner
        import warp

        warp.config.log_level = warp.LOG_WARNING
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError, FileExistsError, RuntimeError) as exc:
        _end_progress()
        print(f"breastbiomech {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
