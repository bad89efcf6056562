"""Fit a compressed case end to end: fitting mesh, parameter space, optimisation, and the
results a user looks at (the predicted image and landmarks at the best parameters, the
landmark errors, the convergence). What ``breastbiomech optimise`` and the Breast Optimization
module run.

Output folder (besides the optimisation's settings.json, evaluations.jsonl, result.json)::

    fitting_mesh.vtu              the fitting mesh (reused on resume)
    segmentation/                 the MR's segmentation from the case's seed points, where the fitting
                                  mesh was made of it (no --mesh or --labels given)
    predicted.nrrd                the FE-predicted compressed MR at the best parameters
    predicted_landmarks.mrk.json  the landmarks moved by the best solution (LPS)
    force_scale.json              where a fitted state records its measured plate force: the scale of
                                  the moduli it fixes, its sd, and the absolute moduli
                                  (:mod:`~BreastBiomechLib.optimisation.force_scale`)
    deformed_mesh.vtu             the fitting mesh with the best solution's ``displacement`` (mm)
    landmark_errors.json          per landmark and summarised as the seed's Table 2 (mm)
    case.json                     the case folder and the fingerprint of its measured image and plates
                                  (with several states, each state's under "states")
    convergence.png               objective and best-so-far against evaluations
    states/<name>/                a joint fit's further measured states: each its predicted.nrrd,
                                  predicted_landmarks.mrk.json, deformed_mesh.vtu and landmark_errors.json

A case with several measured states (:mod:`BreastBiomechLib.io.case_layout`) is fitted jointly by
default (:mod:`~BreastBiomechLib.optimisation.states`: one set of materials, each state its own
plates); the files above without a state's folder are the first state's.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from BreastBiomechLib.io.atomic import write_json_atomically
from BreastBiomechLib.io.case_layout import (FIRST_STATE, REFERENCE_LANDMARKS, STATE_LANDMARKS, STATES, CaseLayout,
                                             PlateForce, read_force)
from BreastBiomechLib.io.claims import claimed
from BreastBiomechLib.io.markups import read_markups, write_markups
from BreastBiomechLib.landmarks import landmark_errors, map_landmarks
from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.optimisation.forward import FittingProblem
from BreastBiomechLib.optimisation.run import OptimisationResult, optimise, solve_best
from BreastBiomechLib.optimisation.space import ParameterSpace
from BreastBiomechLib.optimisation.states import JointProblem
from BreastBiomechLib.solver import DynamicRelaxation
from BreastBiomechLib.timing import staged

LANDMARK_ERRORS = "landmark_errors.json"  # per landmark and summarised (mm)
FORCE_SCALE = "force_scale.json"  # the moduli's scale a measured plate force fixes


@dataclass
class FitSettings:
    """How to fit: the ``model`` variant, the ``free`` parameter names ("E", "nu", "eta"; "fibre"
    for the fibre angles, "offset" for the plates' offsets), the anisotropic ``fibre``
    direction (LPS; where "fibre" is free, the start), the fitting mesh's ``edge_mm``, the ``optimiser``, ``budget``
    (evaluations), ``seconds`` (wall time, None: none), ``seed``, the ``objective``, NMI
    ``bins``, the forward solves' relaxation ``tolerance_mm``, the CMA-ES ``population``."""

    model: str = "aniso-hetero"
    free: tuple[str, ...] = ("E", "nu", "eta")
    fibre: tuple[float, float, float] = (0.0, 0.0, 1.0)
    edge_mm: float = 4.0
    optimiser: str = "hybrid"
    budget: int = 500
    seconds: float | None = None
    seed: int = 0
    objective: str = "nmi"
    bins: int = 64
    tolerance_mm: float = 0.01
    population: int | None = None


@dataclass
class CaseFit:
    """A finished fit: the optimisation ``result``, the ``landmark_errors`` summary (the seed's
    Table 2 figures, mm), the output ``folder`` and, where a fitted state records its measured
    plate force, the ``force_scale`` record (force_scale.json)."""

    result: OptimisationResult
    landmark_errors: dict | None
    folder: Path
    force_scale: dict | None = None


@staged("fit")
def fit_compressed_case(case_dir: str | Path, out_dir: str | Path, settings: FitSettings | None = None,
                        labels: str | Path | None = None, mesh_path: str | Path | None = None,
                        resume: bool = False, device=None,
                        progress: Callable[[int, int, float, str], bool | None] | None = None,
                        states: list[str] | None = None) -> CaseFit:
    """Fit ``settings.model`` to the compressed case in ``case_dir`` (a phantom case folder with
    its ``compressed/`` part, :mod:`BreastBiomechLib.phantom.compressed_files`) and write the
    results to ``out_dir``. The fitting mesh is ``mesh_path`` (a ``breastbiomech mesh`` .vtu), or
    made from ``labels`` (a segmentation's label map) at ``settings.edge_mm``, or, with neither,
    from the segmentation of the case's MR from its seed points (``seeds_muscle.mrk.json``, and
    ``seeds_tumour.mrk.json`` where it has a tumour; :func:`~BreastBiomechLib.segmentation.segment_tissues`,
    written to ``out_dir/segmentation``), as a clinic's case would be; a case without seed points
    is refused (a resumed fit takes its own mesh). A phantom case's labels.nrrd is its ground
    truth, which a fit meant to be realistic never meshes by default; pass it as ``labels`` only on
    purpose (a fit on the truth, to tell the segmentation's share of an error from the model's).
    ``states``: the measured states fitted (names; default every state of the case, jointly
    where there are several: :mod:`~BreastBiomechLib.optimisation.states`)."""
    from BreastBiomechLib.io.images import read_image, read_label_map
    from BreastBiomechLib.io.meshes import read_vtu, write_vtu
    from BreastBiomechLib.phantom.compressed_files import read_compressed

    settings = settings or FitSettings()
    case = Path(case_dir)
    layout = CaseLayout(case)
    out = Path(out_dir)
    segment = mesh_path is None and labels is None and not (resume and (out / "fitting_mesh.vtu").is_file())
    if segment and not layout.seeds_muscle.is_file():
        raise ValueError(f"no fitting mesh: {case} has no seed points on the pectoral muscle ({layout.seeds_muscle.name}) to "
                         "segment its MR from; add them (Breast Segmentation module, or `breastbiomech phantom` "
                         "writes them), or pass --mesh MESH.vtu (`breastbiomech mesh` of your segmentation) or "
                         "--labels SEG.nrrd (a segmentation's label map, meshed at --edge-mm). A phantom case's "
                         f"{layout.truth_labels} is its ground truth: a fit does not mesh it unless --labels names "
                         "it on purpose")
    first = read_compressed(case)
    layout.check()
    names = fitted_states(layout, states)
    measured = {name: first if name == FIRST_STATE else read_compressed(case, name) for name in names}
    undeformed = read_image(layout.mr)
    reference = read_markups(layout.landmarks) if layout.landmarks.is_file() else None
    if reference is not None and measured[names[0]].landmarks is None:
        raise ValueError(f"{case}: the reference landmarks ({REFERENCE_LANDMARKS}) have no measured counterpart in "
                         f"{FIRST_STATE}/{STATE_LANDMARKS}; add it, or remove both to fit without landmarks")
    if len(names) > 1 and "offset" in settings.free:
        raise ValueError(f"{case}: the plates' offsets are fitted for one state's plates; fit the states "
                         f"{', '.join(names)} jointly without 'offset' free, or one state (--states NAME) with it")
    with claimed(out, "a fit of a compressed case"):
        out.mkdir(parents=True, exist_ok=True)
        if resume and (out / "case.json").is_file():  # its evaluations are of the states it began with
            begun = recorded_states(out)
            if begun != names:
                raise ValueError(f"{out}: cannot resume a fit of the states {', '.join(begun)} with "
                                 f"{', '.join(names)}: resume with --states {' '.join(begun)}, or start a new folder")
        write_json_atomically(out / "case.json", case_record(case, names))
        mesh_file = out / "fitting_mesh.vtu"
        if mesh_path is not None:
            mesh = read_vtu(mesh_path)
        elif resume and mesh_file.is_file():
            mesh = read_vtu(mesh_file)
        else:
            from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels

            nipple = reference.position("nipple") if reference is not None and "nipple" in reference.labels else None
            label_map = segmented_labels(case, undeformed, out / "segmentation") if segment else read_label_map(labels)
            mesh = mesh_labels(label_map, MeshSettings(edge_mm=settings.edge_mm), nipple_mm=nipple).mesh
        write_vtu(mesh_file, mesh)
        space = ParameterSpace.for_model(settings.model, np.unique(np.asarray(mesh.cell_data["tissue"]).astype(int)),
                                         free=settings.free, fibre=settings.fibre,
                                         plates=len(measured[names[0]].plates) if "offset" in settings.free else 0)
        relaxation = DynamicRelaxation(tolerance_mm=settings.tolerance_mm)
        problems = {name: FittingProblem(space, mesh, undeformed, m.image, m.plates,
                                         landmarks=(reference, m.landmarks) if reference is not None else None,
                                         objective=settings.objective, bins=settings.bins, relaxation=relaxation,
                                         device=device)
                    for name, m in measured.items()}
        problem = problems[names[0]] if len(names) == 1 else JointProblem(problems)
        result = optimise(problem, settings.optimiser, settings.budget, settings.seconds, settings.seed, out, resume,
                          progress, population=settings.population)

        forces = {name: read_force(layout.state(name)) for name in names if layout.state(name).force.is_file()}
        result, errors, scale = write_fit_outputs(out, problem, result, forces)
        return CaseFit(result, errors, out, scale)


def segmented_labels(case: Path, image, out: Path):
    """The label map of ``image`` (the case's undeformed MR) segmented from the case's seed points
    (:attr:`~BreastBiomechLib.io.case_layout.CaseLayout.seeds_muscle`, and ``seeds_tumour`` where present), the segmentation written to
    ``out`` (labels, probabilities, bias field)."""
    from BreastBiomechLib.io.segmentation import write_segmentation
    from BreastBiomechLib.segmentation import segment_tissues

    layout = CaseLayout(case)
    tumour = read_markups(layout.seeds_tumour).positions if layout.seeds_tumour.is_file() else None
    result = segment_tissues(image, read_markups(layout.seeds_muscle).positions, tumour)
    write_segmentation(result, out, {"segmented_for": "the fitting mesh (seed points of the case)"})
    return result.labels


def case_record(case_dir: str | Path, states: list[str] | None = None) -> dict:
    """What a fit folder's case.json records of the case it fitted: the case folder and the
    fingerprint of its first state's measured image and plates, and with several ``states``
    (names) each one's fingerprint."""
    from BreastBiomechLib.phantom.compressed_files import case_fingerprint

    case = Path(case_dir)
    record = {"case_dir": str(case.resolve()), "fingerprint": case_fingerprint(case)}
    if states and list(states) != [FIRST_STATE]:
        record["states"] = {name: case_fingerprint(case, name) for name in states}
    return record


def recorded_states(fit_dir: str | Path) -> list[str]:
    """The measured states a fit in ``fit_dir`` fitted, as its case.json records them (:func:`case_record`;
    the first state alone where it records none)."""
    recorded = Path(fit_dir) / "case.json"
    states = json.loads(recorded.read_text()).get("states") if recorded.is_file() else None
    return list(states) if states else [FIRST_STATE]


def fitted_states(layout: CaseLayout, chosen: list[str] | None) -> list[str]:
    """The measured states a fit of the case ``layout`` uses: ``chosen`` (names, in the case's
    order, the first state among them) or, with None, every state of the case. A ValueError
    names a state the case does not hold."""
    present = layout.state_names()
    if chosen is None:
        return present
    unknown = [name for name in chosen if name not in present]
    if unknown:
        raise ValueError(f"{layout.root}: no measured state {', '.join(map(repr, unknown))}; the case holds "
                         f"{', '.join(present)}")
    if FIRST_STATE not in chosen:
        raise ValueError(f"the fit's states include the first ({FIRST_STATE}): the fit's files, and the diagnosis "
                         "that reads them, are that state's")
    return [name for name in present if name in chosen]


def write_fit_outputs(out: str | Path, problem: FittingProblem | JointProblem, result: OptimisationResult,
                      forces: dict[str, PlateForce] | None = None) -> tuple:
    """The files a user looks at of an ended optimisation of ``problem`` in its folder ``out``
    (the module's list; not case.json): the best parameters solved alone (a stand-in where they no
    longer solve, :func:`~BreastBiomechLib.optimisation.run.solve_best`), the fitting mesh and its
    solution, the predicted image, with landmarks the moved landmarks and their errors, the
    convergence picture; for a joint fit the first state's in ``out`` and each further state's
    in ``out``/states/<name>; with the measured plate ``forces`` of fitted states (by state
    name) the absolute moduli they give (force_scale.json). Returns the (possibly stood-in)
    result, the first state's landmark-error summary (None without landmarks) and the force
    scale's record (None without forces)."""
    from BreastBiomechLib.io.meshes import write_vtu

    out = Path(out)
    result, best = solve_best(problem, result, out)
    write_vtu(out / "fitting_mesh.vtu", problem.mesh)
    states = problem.problems if isinstance(problem, JointProblem) else {FIRST_STATE: problem}
    solutions = best.solutions if isinstance(problem, JointProblem) else {FIRST_STATE: best}
    errors = None
    for k, (name, state) in enumerate(states.items()):
        folder = out if k == 0 else out / STATES / name
        folder.mkdir(parents=True, exist_ok=True)
        summary = _write_state_outputs(folder, state, solutions[name].displacement)
        errors = summary if k == 0 else errors
    scale = _write_force_scale(out, states, solutions, forces, result) if forces else None
    save_convergence(out / "convergence.png", result)
    return result, errors, scale


def _write_force_scale(out: Path, states: dict, solutions: dict, forces: dict[str, PlateForce],
                       result: OptimisationResult) -> dict:
    """force_scale.json of the fit in ``out``: the scale the measured ``forces`` fix and the
    absolute moduli, or why the fit's model does not allow one (``reason``). Its record."""
    from BreastBiomechLib.optimisation.force_scale import force_scale, not_scale_free, predicted_force

    why = not_scale_free(next(iter(states.values())).model)
    if why:
        record = {"scale": None, "reason": why}
    else:
        records = {name: (force, predicted_force(solutions[name], states[name].model.loading.plates, force.plate))
                   for name, force in forces.items() if name in states}
        record = force_scale(records).to_dict(result.materials)
    write_json_atomically(out / FORCE_SCALE, record)
    return record


def _write_state_outputs(out: Path, problem: FittingProblem, displacement: np.ndarray) -> dict | None:
    """One measured state's predicted image, deformed mesh and, with landmarks, the moved
    landmarks and their errors, in ``out``; the landmark-error summary (None without landmarks)."""
    from BreastBiomechLib.io.images import write_image
    from BreastBiomechLib.io.meshes import write_vtu

    mesh = problem.mesh
    write_image(out / "predicted.nrrd", problem.predict(displacement).image)
    write_vtu(out / "deformed_mesh.vtu", TetMesh(mesh.nodes, mesh.tets, {**mesh.point_data,
                                                                          "displacement": displacement},
                                                 dict(mesh.cell_data)))
    if problem.landmarks is None:
        return None
    reference, measured = problem.landmarks
    moved = map_landmarks(mesh, displacement, reference)
    write_markups(out / "predicted_landmarks.mrk.json", moved, name="Predicted landmarks")
    table = landmark_errors(reference, moved, measured)
    errors = table.summary()
    write_json_atomically(out / LANDMARK_ERRORS, {**errors, "per_landmark": {
        label: {"displacement_mm": float(d), "error_mm": float(e)}
        for label, d, e in zip(table.labels, table.displacement_mm, table.error_mm)}})
    return errors


@staged("pictures")
def save_convergence(path: str | Path, result: OptimisationResult) -> Path:
    """A PNG of each evaluation's objective and the best so far against the evaluation count."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    values = np.array([e.objective for e in result.evaluations])
    figure, axes = plt.subplots(figsize=(6, 3.5), dpi=100)
    axes.plot(np.arange(1, len(values) + 1), values, ".", color="0.6", label="evaluation")
    axes.plot(np.arange(1, len(values) + 1), np.minimum.accumulate(values), "-", color="C3", label="best so far")
    axes.set_xlabel("forward solves")
    axes.set_ylabel("objective (-NMI)" if result.best.objective < 0 else "objective")
    axes.legend(loc="upper right")
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)
    return Path(path)
