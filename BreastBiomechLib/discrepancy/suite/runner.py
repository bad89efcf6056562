"""Running the hidden-effect suite: per anatomy a phantom, its truth mesh, the segmentation of its
MR and the fitting mesh of that segmentation; per case a truth simulation with the hidden effect,
a material fit and the diagnosis, on a copy of the case that holds only what a clinic would have.

The anatomies and the cases run as cohort tasks (:mod:`BreastBiomechLib.cohort`: a local Dask
cluster by default, one worker per GPU, or an existing cluster). Folder layout (every stage is
skipped when its output exists, so a run resumes)::

    anatomy<N>/phantom/          the phantom with its truth (labels, fractions, signal)
    anatomy<N>/truth_mesh.vtu    the truth mesh (of the truth labels; finer than the fitting mesh)
    anatomy<N>/segmentation/     the segmentation of the MR from its seed points
    anatomy<N>/fitting_mesh.vtu  the fitting mesh of the segmentation (never of the truth labels)
    anatomy<N>/<kind>_mesh-<E>mm.vtu  a varied case's truth or fitting mesh at another element size
    anatomy<N>/prepared.json     the anatomy's figures (Dice, mesh sizes, seconds)
    <case>/truth/compressed/     the truth simulation's case with its truth files
    <case>/measured/             what the fit and the diagnosis read: mr.nrrd, landmarks, seed
                                 points, compressed/{mr.nrrd, landmarks.mrk.json, plates.json}
    <case>/fit/                  ``breastbiomech optimise`` output
    <case>/diagnosis/            ``breastbiomech diagnose`` output
    <case>/result.json           the case's scores (:mod:`~BreastBiomechLib.discrepancy.suite.scores`)
    <case>/error.json            the error of a case that failed (a rerun tries it again)
    failures.log                 the failed tasks' tracebacks

Frames and units as everywhere: LPS millimetres, pascal.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from BreastBiomechLib.cohort import Task, place, run_tasks
from BreastBiomechLib.discrepancy.effects import library
from BreastBiomechLib.discrepancy.observations import NoiseModel
from BreastBiomechLib.discrepancy.suite.cases import SuiteCase
from BreastBiomechLib.discrepancy.suite.scores import case_result
from BreastBiomechLib.discrepancy.suite.varied import anatomy_parameters
from BreastBiomechLib.discrepancy.variants import solve_variants
from BreastBiomechLib.io.atomic import write_json_atomically
from BreastBiomechLib.io.case_layout import STATES
from BreastBiomechLib.io.claims import holder_of, is_stale
from BreastBiomechLib.io.markups import read_markups
from BreastBiomechLib.landmarks import Landmarks, map_landmarks
from BreastBiomechLib.solver.placement import MOVING as MOVING_PLATES

# what a clinic has of a compressed case: the fit and the diagnosis see nothing else
MEASURED_FILES = ("mr.nrrd", "landmarks.mrk.json", "seeds_muscle.mrk.json", "seeds_tumour.mrk.json",
                  "compressed/mr.nrrd", "compressed/landmarks.mrk.json", "compressed/plates.json")


@dataclass
class SuiteSettings:
    """How the suite's cases are made and fitted: the plates close by ``compression`` of the
    breast's thickness (LR); phantom voxels ``spacing_mm`` (None: the presets' 1 x 1 x 2.5 mm);
    ``truth_edge_mm`` the truth mesh's element size, ``fit_edge_mm`` the fitting mesh's (of the
    segmentation, its surface smoothed by ``fit_blur_mm`` and made of ``fit_surface_edge_mm``
    triangles, since the diagnosis compares the skin; tissue interfaces refined when
    ``refine_interfaces``); the material fit
    (iso-hetero, E per tissue, CMA-ES) has ``fit_budget`` forward solves in generations of
    ``fit_population``; the diagnosis at most ``rounds`` rounds over the whole library. The
    measured landmarks of both images are the truth's moved by a localisation error of
    ``landmark_noise_mm`` per coordinate (one sd; a person marking them), so that the fit and
    the diagnosis meet landmarks as uncertain as a clinic's; the diagnosis is told that sd, as a
    user gives theirs (``--landmark-sd-mm``). The plates' flat faces end
    ``chest_clearance_mm`` anterior to the chest (None: the plate travel, see
    :func:`~BreastBiomechLib.solver.placement.plate_contacts`), in rounded edges. ``moving_plate``:
    which plate closes on the breast (:class:`~BreastBiomechLib.phantom.compressed.TruthModel`):
    both by default, half the travel each; "second" is the seed's rig for the phantoms' left
    breasts (the lateral plate towards the held medial one)."""

    compression: float = 0.4
    spacing_mm: tuple[float, float, float] | None = None
    truth_edge_mm: float = 3.0
    fit_edge_mm: float = 6.0
    fit_surface_edge_mm: float = 3.0
    refine_interfaces: bool = True
    fit_blur_mm: float = 0.8
    fit_budget: int = 60
    fit_population: int = 12
    rounds: int = 3
    landmark_noise_mm: float = 0.35
    effects: list[str] | None = field(default=None)
    chest_clearance_mm: float | None = None
    moving_plate: str = "both"

    def __post_init__(self) -> None:
        """Refuse settings no case could be made or fitted with, before anything runs (and
        before a run records them in its folder's settings.json)."""
        checks = [(0.0 < self.compression <= 0.7, f"compression is a fraction of the breast's thickness in (0, 0.7], "
                                                  f"not {self.compression}"),
                  (self.truth_edge_mm > 0 and self.fit_edge_mm > 0 and self.fit_surface_edge_mm > 0,
                   "the truth and fitting meshes' edges must be positive (mm)"),
                  (self.fit_blur_mm >= 0, f"fit_blur_mm must be >= 0 (mm), not {self.fit_blur_mm}"),
                  (self.fit_population >= 2, f"the fit's population needs at least 2 models, not {self.fit_population}"),
                  (self.fit_budget >= self.fit_population, f"the fit's budget ({self.fit_budget} solves) must hold one "
                                                           f"generation of {self.fit_population}"),
                  (self.rounds >= 1, f"the diagnosis needs at least one round, not {self.rounds}"),
                  (self.landmark_noise_mm >= 0, f"landmark_noise_mm must be >= 0, not {self.landmark_noise_mm}"),
                  (self.chest_clearance_mm is None or self.chest_clearance_mm >= 0,
                   f"chest_clearance_mm must be >= 0 (mm), not {self.chest_clearance_mm}"),
                  (self.moving_plate in MOVING_PLATES,
                   f"moving_plate is one of {MOVING_PLATES}, not {self.moving_plate!r}")]
        if self.spacing_mm is not None:
            checks.append((len(self.spacing_mm) == 3 and all(0.3 <= v <= 4.0 for v in self.spacing_mm),
                           f"spacing_mm needs three voxel sizes of 0.3-4 mm, not {self.spacing_mm}"))
        problems = [message for ok, message in checks if not ok]
        if problems:
            raise ValueError("suite settings: " + "; ".join(problems))


def write_json(path: Path, document: dict) -> None:
    """Write ``document`` to ``path`` atomically (:mod:`BreastBiomechLib.io.atomic`)."""
    write_json_atomically(path, document, indent=1)


class _Lock:
    """A lock file made with O_EXCL and holding its process id and host, so that suite runs side by
    side on one folder prepare an anatomy or a case once. A lock whose process on this host is
    gone (a run killed while it held it) is taken over, as a claimed folder is
    (:mod:`~BreastBiomechLib.io.claims`): a suite run killed and started again goes on."""

    def __init__(self, path: Path, wait_s: float = 3600.0):
        self.path, self.wait_s = path, wait_s

    def __enter__(self):
        started = time.monotonic()
        record = json.dumps({"pid": os.getpid(), "host": socket.gethostname()}) + "\n"
        while True:
            try:
                descriptor = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                if is_stale(self.path, holder_of(self.path)):
                    self.path.unlink(missing_ok=True)
                    continue
                if time.monotonic() - started > self.wait_s:
                    raise TimeoutError(f"{self.path} is held for over {self.wait_s:.0f} s by a live process "
                                       f"({holder_of(self.path)}); wait for it, or stop that run") from None
                time.sleep(2.0)
                continue
            with os.fdopen(descriptor, "w") as file:
                file.write(record)
            return self

    def __exit__(self, *exc):
        self.path.unlink(missing_ok=True)


def prepare_anatomy(number: int, out: Path, settings: SuiteSettings, device=None,
                    say: Callable[[str], None] = lambda m: None) -> dict:
    """The phantom of suite anatomy ``number`` (:func:`~BreastBiomechLib.discrepancy.suite.varied.anatomy_parameters`),
    its truth mesh, the segmentation of its MR and the fitting mesh of the segmentation, in
    ``out/anatomy<number>`` (made once; see the module)."""
    from BreastBiomechLib.io.images import read_image
    from BreastBiomechLib.io.meshes import write_vtu
    from BreastBiomechLib.io.segmentation import write_segmentation
    from BreastBiomechLib.phantom import generate_phantom, write_phantom
    from BreastBiomechLib.segmentation import dice_per_tissue, segment_tissues

    folder = out / f"anatomy{number}"
    done = folder / "prepared.json"
    folder.mkdir(parents=True, exist_ok=True)
    with _Lock(folder / ".lock"):
        if done.is_file():
            return json.loads(done.read_text())
        figures, started = {}, time.perf_counter()
        say(f"anatomy {number}: phantom")
        params = anatomy_parameters(number)
        if settings.spacing_mm is not None:
            params.spacing_mm = tuple(settings.spacing_mm)
        case = generate_phantom(params)
        write_phantom(case, folder / "phantom", overview=False)
        figures["phantom"] = {"volume_cm3": case.summary["breast_volume_cm3"],
                              "density": case.summary["glandular_density"], "seconds": time.perf_counter() - started}
        say(f"anatomy {number}: truth mesh ({settings.truth_edge_mm:g} mm)")
        t = time.perf_counter()
        truth_mesh = _truth_mesh(case.labels, case.landmarks.position("nipple"), settings.truth_edge_mm)
        write_vtu(folder / "truth_mesh.vtu", truth_mesh)
        figures["truth_mesh"] = {"tets": len(truth_mesh.tets), "seconds": time.perf_counter() - t}
        say(f"anatomy {number}: segmentation of the MR")
        t = time.perf_counter()
        scan = folder / "phantom"
        tumour_seeds = scan / "seeds_tumour.mrk.json"
        result = segment_tissues(read_image(scan / "mr.nrrd"), read_markups(scan / "seeds_muscle.mrk.json").positions,
                                 read_markups(tumour_seeds).positions if tumour_seeds.is_file() else None)
        dice = dice_per_tissue(result.labels, case.labels)
        write_segmentation(result, folder / "segmentation", {"dice_vs_truth": dice})
        figures["segmentation"] = {"dice": dice, "seconds": time.perf_counter() - t}
        say(f"anatomy {number}: fitting mesh of the segmentation ({settings.fit_edge_mm:g} mm)")
        t = time.perf_counter()
        mesh = _fitting_mesh(result.labels, read_markups(scan / "landmarks.mrk.json").position("nipple"), settings)
        write_vtu(folder / "fitting_mesh.vtu", mesh)
        figures["fitting_mesh"] = {"nodes": len(mesh.nodes), "tets": len(mesh.tets),
                                   "seconds": time.perf_counter() - t}
        write_json(done, figures)
        return figures


def _truth_mesh(labels, nipple_mm, edge_mm: float, skin_mm: float | None = None):
    """The truth mesh of a phantom's truth ``labels`` at ``edge_mm``, with skin triangles fine
    enough for a truth skin of ``skin_mm`` (:func:`~BreastBiomechLib.phantom.compressed.truth_mesh_settings`)."""
    from BreastBiomechLib.mesh.from_labels import mesh_labels
    from BreastBiomechLib.phantom.compressed import truth_mesh_settings

    return mesh_labels(labels, truth_mesh_settings(edge_mm, skin_mm), nipple_mm=nipple_mm).mesh


def _fitting_mesh(segmentation_labels, nipple_mm, settings: SuiteSettings):
    """The fitting mesh of a segmentation's labels under ``settings`` (never of the truth labels)."""
    from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels

    return mesh_labels(segmentation_labels, MeshSettings(edge_mm=settings.fit_edge_mm,
                                                         surface_edge_mm=settings.fit_surface_edge_mm,
                                                         refine_interfaces=settings.refine_interfaces,
                                                         blur_mm=settings.fit_blur_mm), nipple_mm=nipple_mm).mesh


def case_settings(case: SuiteCase, settings: SuiteSettings) -> SuiteSettings:
    """``settings`` with what ``case`` drew (a varied suite's case) in place of the run's."""
    return replace(settings, **case.drawn) if case.drawn else settings


def anatomy_mesh(anatomy: Path, kind: str, mine: SuiteSettings, run: SuiteSettings, skin_mm: float | None = None) -> Path:
    """The path of anatomy folder ``anatomy``'s ``kind`` ("truth" or "fitting") mesh at the element
    size of a case's settings ``mine``: the prepared one where it is the run's (``run``), else
    ``<kind>_mesh-<edge>mm.vtu``, made once (under the anatomy's lock) from the phantom's truth
    labels or the segmentation's labels; a truth mesh for a hidden skin of ``skin_mm`` with skin
    triangles fine enough to hold it, ``truth_mesh-<edge>mm-skin<skin>mm.vtu``."""
    from BreastBiomechLib.io.images import read_image
    from BreastBiomechLib.io.meshes import write_vtu

    edge = mine.truth_edge_mm if kind == "truth" else mine.fit_edge_mm
    skin_mm = skin_mm if kind == "truth" else None
    if skin_mm is None and edge == (run.truth_edge_mm if kind == "truth" else run.fit_edge_mm):
        return anatomy / f"{kind}_mesh.vtu"
    path = anatomy / f"{kind}_mesh-{edge:g}mm{'' if skin_mm is None else f'-skin{skin_mm:g}mm'}.vtu"
    with _Lock(anatomy / ".lock"):
        if not path.is_file():
            nipple = read_markups(anatomy / "phantom" / "landmarks.mrk.json").position("nipple")
            if kind == "truth":
                mesh = _truth_mesh(read_image(anatomy / "phantom" / "labels.nrrd"), nipple, edge, skin_mm)
            else:
                mesh = _fitting_mesh(read_image(anatomy / "segmentation" / "labels.nrrd"), nipple, mine)
            write_vtu(path, mesh)
    return path


def hidden_truth(case: SuiteCase, settings: SuiteSettings) -> dict:
    """The :class:`~BreastBiomechLib.phantom.compressed.TruthModel` fields that hide ``case``'s
    effect under ``settings``: a hidden plate tilt is put on the plate that moves where only the
    second one does (a held plate tilted about its final point would stand off the tissue)."""
    truth = dict(case.hidden.truth)
    if truth.get("plate_tilt_deg") is not None and settings.moving_plate == "second":
        for key in ("plate_tilt_deg", "plate_pivot_mm"):
            if truth.get(key) is not None:
                truth[key] = list(reversed(truth[key]))
    return truth


def measured_copy(case_dir: Path, into: Path, landmark_noise_mm: float = 0.0, seed: int = 0,
                  states: bool = False) -> Path:
    """Copy of the compressed case in ``case_dir`` holding only :data:`MEASURED_FILES` (what a
    clinic would have: no labels, no truth), in ``into``; its landmarks (undeformed and
    compressed) moved by a localisation error drawn from N(0, ``landmark_noise_mm``²) per
    coordinate (mm; random numbers from ``seed``). ``states``: also each further state's scan,
    landmarks and plates (``states/<name>/``), their landmarks' errors drawn after the first
    state's (which are the same as without the states)."""
    from BreastBiomechLib.io.markups import read_markups, write_markups

    if landmark_noise_mm < 0:
        raise ValueError(f"the landmarks' localisation error is an sd in mm (>= 0), not {landmark_noise_mm}")
    if into.exists():
        shutil.rmtree(into)
    rng = np.random.default_rng(seed)
    names = list(MEASURED_FILES)
    if states:
        from BreastBiomechLib.io.case_layout import STATE_LANDMARKS, STATE_MR, STATE_PLATES, CaseLayout

        names += [f"{STATES}/{state}/{file}" for state in CaseLayout(case_dir).state_names()
                  for file in (STATE_MR, STATE_LANDMARKS, STATE_PLATES)]
    for name in names:
        source = case_dir / name
        if not source.is_file():
            continue
        (into / name).parent.mkdir(parents=True, exist_ok=True)
        if name.endswith("landmarks.mrk.json") and landmark_noise_mm > 0:
            exact = read_markups(source)
            marked = exact.positions + landmark_noise_mm * rng.standard_normal(exact.positions.shape)
            write_markups(into / name, Landmarks(marked, exact.labels, exact.descriptions),
                          name="Landmarks" if name == "landmarks.mrk.json" else "Compressed landmarks")
        else:
            shutil.copy2(source, into / name)
    return into


def scored_against_truth(folder: Path, fit_dir: Path, rounds: list[dict], device=None,
                         measured: Path | None = None) -> tuple[float, dict]:
    """For scoring only (it reads the case's truth folder, after the diagnosis has answered):
    the NMI against the measured image of the image the truth parameters predict (the undeformed
    MR warped through the truth mesh's displacement: the ceiling of any fit, measured as the fit
    measures its own), and the mean landmark error (mm) of the fitted model before the first
    round and after the last refit against the truth's exact landmarks ({"before", "after"}: the
    exact undeformed landmarks moved by each model's displacement against the exact compressed
    ones; the measured landmarks carry a localisation error that would floor the figure), all of
    the first state; ``measured`` the case copy the fit read (default ``folder``/measured)."""
    from BreastBiomechLib.discrepancy.fitted import load_fitted_case
    from BreastBiomechLib.discrepancy.session import state_from_record
    from BreastBiomechLib.discrepancy.state import ModelState
    from BreastBiomechLib.io.images import read_image
    from BreastBiomechLib.io.meshes import read_vtu
    from BreastBiomechLib.warping import ImageWarper

    measured = measured or folder / "measured"
    fitted = load_fitted_case(measured, fit_dir, device=device)
    truth = read_vtu(folder / "truth" / "compressed" / "truth_mesh.vtu")
    warper = ImageWarper(truth, read_image(measured / "mr.nrrd"), read_image(measured / "compressed" / "mr.nrrd"),
                         device=device)
    ceiling = float(fitted.problem.similarity.nmi(warper.warp(truth.point_data["displacement"])))

    reference = read_markups(folder / "truth" / "landmarks.mrk.json")
    compressed = read_markups(folder / "truth" / "compressed" / "landmarks.mrk.json")
    displacements = {}
    if (fit_dir / "deformed_mesh.vtu").is_file():  # the fit's own solution, as the diagnosis starts from it
        displacements["before"] = read_vtu(fit_dir / "deformed_mesh.vtu").point_data["displacement"]
    states = {} if displacements else {"before": ModelState(fitted, fitted.z)}
    last = next((r for r in reversed(rounds) if r.get("added")), None)
    if last is not None:
        states["after"] = state_from_record(fitted, last, library(fitted, list(last["state_after"]["added"])))
    if states:
        outcomes = solve_variants([s.variant() for s in states.values()], fitted.mesh.nodes, fitted.relaxation,
                                  device)
        displacements |= {key: fitted.first(o.displacement) for key, o in zip(states, outcomes) if o.ok}
    errors = {}
    for key, displacement in displacements.items():
        moved = map_landmarks(fitted.mesh, displacement, reference)
        errors[key] = float(np.linalg.norm(moved.positions - compressed.positions, axis=1).mean())
    return ceiling, errors


def run_case(case: SuiteCase, out: Path, settings: SuiteSettings, device=None,
             say: Callable[[str], None] = lambda m: None) -> dict:
    """Make, fit and diagnose one suite case in ``out/<case.name>``; returns (and writes) its
    ``result.json`` (see :func:`~BreastBiomechLib.discrepancy.suite.scores.case_result`). A
    second suite run on the same folder that reaches the case while the first makes it waits for
    it (a lock file in the case's folder) and takes its result."""
    folder = out / case.name
    result_path = folder / "result.json"
    if result_path.is_file():
        return json.loads(result_path.read_text())
    folder.mkdir(parents=True, exist_ok=True)
    with _Lock(folder / ".lock", wait_s=4 * 3600.0):  # suite runs side by side on the folder make it once
        if result_path.is_file():
            return json.loads(result_path.read_text())
        result = _make_fit_and_diagnose(case, out, settings, device, say)
        write_json(result_path, result)
    (folder / "error.json").unlink(missing_ok=True)  # an earlier attempt's
    return result


def _make_fit_and_diagnose(case: SuiteCase, out: Path, settings: SuiteSettings, device, say) -> dict:
    """The body of :func:`run_case` (under the case's lock): what is missing of the case's truth,
    measured copy, fit and diagnosis made, then scored against the truth."""
    from BreastBiomechLib.discrepancy.suite.two_state import realised_separations
    from BreastBiomechLib.io.meshes import read_vtu
    from BreastBiomechLib.phantom.compressed import TruthModel, compress_phantom
    from BreastBiomechLib.phantom.compressed_files import write_compressed
    from BreastBiomechLib.phantom.files import read_phantom

    folder = out / case.name
    anatomy = out / f"anatomy{case.anatomy}"
    prepared = prepare_anatomy(case.anatomy, out, settings, device, say)
    run_settings, settings = settings, case_settings(case, settings)
    seconds = {}
    truth_dir = folder / "truth"
    if not (truth_dir / "compressed" / "truth.json").is_file():
        say(f"{case.name}: truth simulation")
        t = time.perf_counter()
        phantom = read_phantom(anatomy / "phantom")
        truth = TruthModel(compression=settings.compression, edge_mm=settings.truth_edge_mm, seed=case.seed,
                           chest_clearance_mm=settings.chest_clearance_mm, moving_plate=settings.moving_plate,
                           **hidden_truth(case, settings))
        compressed = compress_phantom(phantom, truth, device=device,
                                      mesh=read_vtu(anatomy_mesh(anatomy, "truth", settings, run_settings,
                                                                 skin_mm=truth.skin[1] if truth.skin else None)))
        for name in ("mr.nrrd", "landmarks.mrk.json", "seeds_muscle.mrk.json", "seeds_tumour.mrk.json"):
            if (anatomy / "phantom" / name).is_file():
                truth_dir.mkdir(parents=True, exist_ok=True)
                shutil.copy2(anatomy / "phantom" / name, truth_dir / name)
        write_compressed(compressed, truth_dir, overview=False)
        seconds["truth"] = time.perf_counter() - t
    measured = folder / "measured"
    if not (measured / "compressed" / "plates.json").is_file():
        measured_copy(truth_dir, measured, settings.landmark_noise_mm, case.seed)
    fitting_mesh = anatomy_mesh(anatomy, "fitting", settings, run_settings)
    fit_dir, diagnosis_dir = folder / "fit", folder / "diagnosis"
    rounds = _fit_and_diagnose(case, measured, fit_dir, diagnosis_dir, fitting_mesh, settings, device, say, seconds,
                               design=case.states == 2)
    say(f"{case.name}: scoring against the truth")
    ceiling, true_errors = scored_against_truth(folder, fit_dir, rounds, device)
    one = case_result(replace(case, states=1), rounds, ceiling, prepared, seconds, true_errors,
                      truth_parameters=case.hidden.truth)
    if case.states == 1:
        return one
    second = _second_state(case, folder, diagnosis_dir, rounds[-1]["round"], settings, device, say, seconds)
    measured = folder / "measured-two-state"
    if not (measured / STATES / second["state"] / "plates.json").is_file():
        measured_copy(truth_dir, measured, settings.landmark_noise_mm, case.seed, states=True)
    fit_dir, diagnosis_dir = folder / "fit-two-state", folder / "diagnosis-two-state"
    rounds = _fit_and_diagnose(case, measured, fit_dir, diagnosis_dir, fitting_mesh, settings, device, say, seconds,
                               stage="two-state ")
    ceiling, true_errors = scored_against_truth(folder, fit_dir, rounds, device, measured=measured)
    second["realised_sigma"] = realised_separations(rounds[0], second)
    return {**case_result(case, rounds, ceiling, prepared, seconds, true_errors, truth_parameters=case.hidden.truth),
            "one_state": one, "second_state": second}


def _fit_and_diagnose(case: SuiteCase, measured: Path, fit_dir: Path, diagnosis_dir: Path, fitting_mesh: Path,
                      settings: SuiteSettings, device, say, seconds: dict, design: bool = False,
                      stage: str = "") -> list[dict]:
    """The material fit of the measured copy ``measured`` (every state it holds, jointly) and its
    diagnosis (with ``design``: then the next measurement designed from it); returns the rounds.
    Each is skipped where its output exists (the diagnosis resumes)."""
    from BreastBiomechLib.discrepancy.acquisitions import KINDS
    from BreastBiomechLib.discrepancy.workflow import run_diagnosis
    from BreastBiomechLib.optimisation.case import FitSettings, fit_compressed_case

    if not (fit_dir / "result.json").is_file():
        say(f"{case.name}: {stage}material fit ({settings.fit_budget} solves)")
        t = time.perf_counter()
        if fit_dir.exists():
            shutil.rmtree(fit_dir)
        fit = FitSettings(model="iso-hetero", free=("E",), edge_mm=settings.fit_edge_mm, optimiser="cmaes",
                          budget=settings.fit_budget, population=settings.fit_population)
        fit_compressed_case(measured, fit_dir, fit, mesh_path=fitting_mesh, device=device)
        seconds[f"{stage}fit".replace(" ", "_")] = time.perf_counter() - t
    say(f"{case.name}: {stage}diagnosis")
    t = time.perf_counter()
    # no residual displacement fields: they are evidence for a person, not part of the verdict the
    # suite scores, and 45 cases' registrations would cost more than their diagnoses
    # told how precisely the landmarks were marked, as a user gives it (--landmark-sd-mm)
    run = run_diagnosis(measured, fit_dir, diagnosis_dir, effects=settings.effects, rounds=settings.rounds,
                        noise=NoiseModel(landmark_sd_mm=settings.landmark_noise_mm),
                        device=device, resume=diagnosis_dir.exists(), registration=None,
                        design=KINDS if design else None, progress=lambda message: say(f"{case.name}: {message}"))
    seconds[f"{stage}diagnosis".replace(" ", "_")] = time.perf_counter() - t
    return run.rounds


def _second_state(case: SuiteCase, folder: Path, diagnosis_dir: Path, last_round: int, settings: SuiteSettings,
                  device, say, seconds: dict) -> dict:
    """The second scan of a two-state case: the acquisition the design made after the one-scan
    diagnosis recommends (over the whole library where that design had nothing undecided to
    design for), made as a further state of the truth. Returns {"acquisition", "state" (its
    state's name), "description",
    "designed_for", "predicted_sigma" (each effect's separation from its rival with it), "rivals",
    "needed_sigma"}; the caller adds "realised_sigma" once the two scans are diagnosed."""
    from BreastBiomechLib.discrepancy.design_record import read_design
    from BreastBiomechLib.discrepancy.suite.two_state import designed_acquisition, state_spec
    from BreastBiomechLib.io.case_layout import CaseLayout
    from BreastBiomechLib.phantom.states import add_states

    record = read_design(diagnosis_dir, last_round)
    if record is None:
        raise RuntimeError(f"{diagnosis_dir}: the one-scan diagnosis made no design after round {last_round}")
    if not record["designed_for"]:
        record = _library_design(case, folder, diagnosis_dir, settings, device, say)
    acquisition = designed_acquisition(record)
    spec = state_spec(acquisition, settings.compression)
    truth_dir = folder / "truth"
    if spec.name not in CaseLayout(truth_dir).state_names():
        say(f"{case.name}: truth of the second scan ({acquisition['description']})")
        t = time.perf_counter()
        phantom = folder.parent / f"anatomy{case.anatomy}" / "phantom"  # the anatomy's, shared by its cases
        add_states(truth_dir, [spec], device=device, overview=False, phantom_dir=phantom)
        seconds["second_truth"] = time.perf_counter() - t
    predicted = {r["effect"]: next((a["separation_sigma"] for a in r["acquisitions"] if a["name"] == acquisition["name"]),
                                   None)
                 for r in record["effects"] if not r.get("skipped")}
    return {"acquisition": acquisition["name"], "state": spec.name, "description": acquisition["description"],
            "designed_for": record["designed_for"], "predicted_sigma": predicted,
            "rivals": {r["effect"]: r.get("rival") for r in record["effects"] if not r.get("skipped")},
            "needed_sigma": next((r["detectable_sigma"] for r in record["effects"]), None)}


def _library_design(case: SuiteCase, folder: Path, diagnosis_dir: Path, settings: SuiteSettings, device, say) -> dict:
    """The next measurement designed for every candidate of the library from the one-scan
    diagnosis's last model (where its rounds told every candidate apart), kept as
    design-library.json in the case's folder."""
    from BreastBiomechLib.discrepancy.acquisitions import KINDS
    from BreastBiomechLib.discrepancy.design import design
    from BreastBiomechLib.discrepancy.session import DiagnosisSession

    path = folder / "design-library.json"
    if path.is_file():
        return json.loads(path.read_text())
    say(f"{case.name}: designing the second scan over the whole library")
    # the diagnosis's last model, features and noise (its measured floor, read from its folder)
    session = DiagnosisSession(folder / "measured", folder / "fit", diagnosis_dir, effects=settings.effects,
                               noise=NoiseModel(landmark_sd_mm=settings.landmark_noise_mm), device=device,
                               resume=True, registration=None)
    made = design(session.fitted, settings.effects, KINDS, noise=session.noise, state=session.state,
                  observations=session.observations, progress=lambda message: say(f"{case.name}: {message}"))
    record = {"undecided": [], "designed_for": [r["effect"] for r in made.effects], **made.to_dict()}
    write_json(path, record)
    return record


def suite_tasks(out: Path, cases: list[SuiteCase], settings: SuiteSettings) -> list:
    """The suite's tasks (:class:`~BreastBiomechLib.cohort.Task`) not yet done in ``out``: each
    anatomy its cases need, then each case (made, fitted, diagnosed, scored), which needs it. The
    anatomies have the higher priority: on a cluster each one lets its cases start on any worker."""
    todo = [case for case in cases if not (out / case.name / "result.json").is_file()]
    tasks = [Task(f"anatomy/{number}", prepare_anatomy_task, {"number": number, "out": str(out), "settings": settings},
                  label=f"anatomy {number}", priority=1)
             for number in sorted({case.anatomy for case in todo})
             if not (out / f"anatomy{number}" / "prepared.json").is_file()]
    tasks += [Task(f"case/{case.name}", run_case_task, {"case": case, "out": str(out), "settings": settings},
                   needs=(f"anatomy/{case.anatomy}",), label=case.name) for case in todo]
    return tasks


def prepare_anatomy_task(number: int, out: str, settings: SuiteSettings, device=None, progress=None) -> dict:
    """A suite task: :func:`prepare_anatomy`."""
    return prepare_anatomy(number, Path(out), settings, device, progress or (lambda message: None))


def run_case_task(case: SuiteCase, out: str, settings: SuiteSettings, device=None, progress=None) -> dict:
    """A suite task: :func:`run_case`; a case that fails leaves its error.json beside its files."""
    try:
        return run_case(case, Path(out), settings, device, progress or (lambda message: None))
    except Exception as error:
        if (Path(out) / case.name).is_dir():
            write_json(Path(out) / case.name / "error.json", {"case": case.name,
                                                               "error": f"{type(error).__name__}: {error}"})
        raise


def run_suite(out, cases: list[SuiteCase], settings: SuiteSettings | None = None, placement=None,
              progress=None) -> list:
    """Run the suite's ``cases`` in ``out`` as tasks (:func:`suite_tasks`) at ``placement``
    (:func:`BreastBiomechLib.cohort.place`; None: a local cluster); a case that fails is
    recorded with its error (error.json, failures.log) and the others go on; a rerun does what is
    missing. ``progress(CohortProgress)`` returning False cancels. Returns the tasks' outcomes."""
    from BreastBiomechLib.optimisation.study import log_failure

    settings = settings or SuiteSettings()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    settings_path = out / "settings.json"
    recorded = json.loads(settings_path.read_text()) if settings_path.is_file() else None
    mine = asdict(settings) | {"spacing_mm": None if settings.spacing_mm is None else list(settings.spacing_mm)}
    if recorded is not None and recorded != mine:
        raise ValueError(f"{out} holds a suite run with other settings ({recorded}); use another --out")
    if recorded is None:
        write_json(settings_path, mine)
    return run_tasks(suite_tasks(out, cases, settings), placement or place(), progress=progress,
                     on_outcome=lambda o: log_failure(out / "failures.log", o))
