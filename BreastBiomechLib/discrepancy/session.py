"""The diagnosis one step at a time: diagnose a round, then add the named effect (or another
candidate the user chooses) with its warm-started refit, or reject it; every step written to the
output folder as it finishes, so that a run resumes and the Breast Discrepancy module, the
Python console and :func:`~BreastBiomechLib.discrepancy.workflow.run_diagnosis` share one path.

Output folder::

    round-<N>.json   each round: the diagnosis (verdict, every statistic), the model before and
                     after (fit parameters, effects added), landmark error, NMI and residual by
                     region before and after the refit; ``added`` (the effect added) or
                     ``rejected`` (candidates the user turned down) once decided
    diagnosis.json   the case and fit, the settings, all rounds and the latest verdict
    floor.json       the measured model-error floor's per-feature discretisation estimate and
                     groups (:mod:`BreastBiomechLib.discrepancy.floor`; with the noise model's
                     floor "measured"), or why it could not be measured (the refined model did
                     not solve: the fixed floor is used, as each round's record and the report say)
    round-<N>-residual-{before,after}.nrrd
                     the residual displacement field of the round's model before and after its refit
                     (vector, LPS mm, on the measured image's grid; Slicer loads it as a vector
                     volume; it is a residual, measured minus model position, not a resampling transform)
    round-<N>-residual.png
                     its magnitude over the measured image, before and after, with the landmark residuals
    round-<N>-kept.npz
                     a round that waited for a decision: its diagnosis kept (sensitivities, refits and,
                     once decided, the refit with the added effect; :mod:`BreastBiomechLib.discrepancy.kept`),
                     so that a later session (another process) decides and shows it without
                     diagnosing the round again; also a round's checkpoint, kept after its solves
                     and statistics and before the registration and its first write, which a
                     resumed run takes up where it was made from the same model, candidates,
                     settings and features (removed when the round is written and waits for no decision)
    design.json, design.md
                     the next measurement (:meth:`DiagnosisSession.design`, ``diagnose --design``): for the
                     candidates the last round could not tell apart, each acquisition's separation
                     (:mod:`BreastBiomechLib.discrepancy.design`); ``round``: the round it was made after
    report.md        the report (:mod:`BreastBiomechLib.discrepancy.report`)

A round is *open* while its verdict asks for a decision (a missing effect or an ambiguous
choice) and none was made; diagnosing again replaces an open round, any other round is followed
by a new one.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from dataclasses import field as dataclass_field
from pathlib import Path

import numpy as np

from BreastBiomechLib.discrepancy.design_record import DESIGN_FILE, DESIGN_MARKDOWN
from BreastBiomechLib.discrepancy.diagnosis import Diagnosis, DiagnosisSettings, adopt, diagnose, region_summary
from BreastBiomechLib.discrepancy.effects import library
from BreastBiomechLib.discrepancy.fitted import FittedCase, load_fitted_case, recorded_solution
from BreastBiomechLib.discrepancy.floor import MeasuredFloor, measure_floor
from BreastBiomechLib.discrepancy.kept import SUFFIX as KEPT
from BreastBiomechLib.discrepancy.kept import load_diagnosis, save_diagnosis
from BreastBiomechLib.discrepancy.observations import NoiseModel, Observations, observations_of
from BreastBiomechLib.discrepancy.regions import feature_regions, regions_of
from BreastBiomechLib.discrepancy.registration import RegistrationSettings, ResidualField
from BreastBiomechLib.discrepancy.report import write_report
from BreastBiomechLib.discrepancy.state import ModelState
from BreastBiomechLib.io.atomic import atomic_path, write_text_atomically
from BreastBiomechLib.io.claims import CLAIM_FILE
from BreastBiomechLib.timing import staged

FLOOR_FILE = "floor.json"  # the measured model-error floor of the session's features
SAME_SOLUTION_MM = 0.01  # two solutions this close (largest node difference) are of the same model
DECISIONS = ("missing effect", "ambiguous")  # verdicts that leave a round open until the user decides


class DiagnosisCancelled(RuntimeError):
    """The progress callback answered False: the step stopped before writing anything."""


def measures(fitted: FittedCase, observations: Observations, displacement: np.ndarray, regions) -> dict:
    """What the report compares before and after a round: landmark errors (mm), NMI against the
    measured image, and the residual by region; in a fit of several measured states the first
    state's landmark errors and NMI, each further state's under ``states`` (by name), the
    residual over every state's features."""
    parts = fitted.split(displacement)
    out = _state_measures(fitted, parts[0])
    residual = observations.residual(displacement)
    out["residual_rms_mm"] = float(np.sqrt(np.mean(residual ** 2)))
    out["regions"] = region_summary(observations, residual, regions)
    if fitted.further:
        out["states"] = {state.name: _state_measures(state, u) for state, u in zip(fitted.further, parts[1:])}
    return out


def _state_measures(fitted: FittedCase, displacement: np.ndarray) -> dict:
    """Landmark errors (mm) and NMI of one measured state ``fitted`` at its solution ``displacement`` (N, 3)."""
    out = {}
    if fitted.reference is not None:
        from BreastBiomechLib.landmarks import map_landmarks

        moved = map_landmarks(fitted.mesh, displacement, fitted.reference)
        errors = np.linalg.norm(moved.positions - fitted.measured.positions, axis=1)
        out["landmark_error_mm"] = {"mean": float(errors.mean()), "max": float(errors.max()),
                                    "per_landmark": dict(zip(fitted.reference.labels, errors.round(3).tolist()))}
    out["nmi"] = float(fitted.problem.similarity.nmi(fitted.problem.warper.warp(displacement)))
    return out


@dataclass
class FieldRecorder:
    """Makes, summarises and saves the residual displacement fields of a run's models (see
    :mod:`~BreastBiomechLib.discrepancy.registration`): the measured body found once, the
    fitting mesh's nodes labelled by region once. In the first measured state (a solution in
    every state is taken at its first state's part)."""

    fitted: FittedCase
    settings: RegistrationSettings
    node_regions: np.ndarray
    body: np.ndarray

    @classmethod
    @staged("residual fields")
    def of(cls, fitted: FittedCase, base_displacement: np.ndarray, settings: RegistrationSettings) -> FieldRecorder:
        import SimpleITK as sitk

        from BreastBiomechLib.segmentation.body import body_mask
        from BreastBiomechLib.segmentation.volume import check_volume

        body = body_mask(sitk.GetArrayFromImage(fitted.measured_image).astype(np.float32),
                         check_volume(fitted.measured_image))
        return cls(fitted, settings, regions_of(fitted, fitted.mesh.nodes, fitted.first(base_displacement)), body)

    last: tuple[np.ndarray, ResidualField] | None = dataclass_field(default=None, repr=False)

    def field(self, displacement: np.ndarray) -> ResidualField:
        """The residual field of the model whose solution is ``displacement``; the last one made
        again where the model is the same (a round's model after its refit is the next round's
        before it: its solution re-solved there differs by under :data:`SAME_SOLUTION_MM`)."""
        from BreastBiomechLib.discrepancy.registration import residual_field_of

        first = self.fitted.first(displacement)
        if (self.last is not None and self.last[0].shape == first.shape
                and float(np.abs(self.last[0] - first).max()) <= SAME_SOLUTION_MM):
            return self.last[1]
        made = residual_field_of(self.fitted, first, self.body, self.settings)
        self.last = (first.copy(), made)
        return made

    @staged("residual fields")
    def summary(self, field: ResidualField, displacement: np.ndarray, path: Path) -> dict:
        """The figures of ``field`` (of the model whose solution is ``displacement``), saved to ``path``."""
        import SimpleITK as sitk

        from BreastBiomechLib.discrepancy.registration import field_by_region

        image = sitk.Cast(field.image(), sitk.sitkVectorFloat32)
        with atomic_path(path) as temporary:
            sitk.WriteImage(image, str(temporary), useCompression=True)
        magnitude = field.magnitude[field.mask]
        return {"file": path.name, "mean_mm": float(magnitude.mean()), "p95_mm": float(np.percentile(magnitude, 95)),
                "accuracy": field.accuracy,
                "regions": field_by_region(field, self.fitted.mesh.nodes, self.fitted.first(displacement),
                                           self.node_regions)}


def state_from_record(fitted: FittedCase, record: dict, effects, when: str = "after") -> ModelState:
    """The model after (``when`` "before": before) a recorded round."""
    by_name = {e.name: e for e in effects}
    after = record[f"state_{when}"]
    state = ModelState(fitted, np.asarray(after["z"], float))
    for name, values in after["added"].items():
        state = state.with_effect(by_name[name], values)
    return state


def is_open(record: dict) -> bool:
    """Whether a round still waits for a decision (see the module docstring)."""
    return (record["diagnosis"]["verdict"] in DECISIONS and not record.get("added")
            and not record.get("rejected"))


class DiagnosisSession:
    """The diagnosis of the fit in ``fit_dir`` of the compressed case ``case_dir``, written to
    ``out_dir`` (a new or empty folder; with ``resume`` the folder of an earlier session of the
    same case and fit, which goes on after its last round). ``effects``: the candidates' names
    (default the whole library); ``settings.refine_iterations`` refine the verdict's effect
    during :meth:`diagnose` (0 leaves the refinement to :meth:`add`); ``registration``: the
    residual displacement field's settings (None: no field). ``progress(message)`` of each step
    returning False cancels it (:class:`DiagnosisCancelled`), before it writes anything; the
    message after a step's last write (the verdict, the effect added) cannot cancel: the step is
    on disk."""

    def __init__(self, case_dir, fit_dir, out_dir, effects=None, noise: NoiseModel | None = None,
                 settings: DiagnosisSettings | None = None, device=None, resume: bool = False,
                 registration: RegistrationSettings | None = RegistrationSettings(),
                 progress: Callable[[str], object] | None = None):
        self.out = Path(out_dir)
        self.case_dir, self.fit_dir = Path(case_dir), Path(fit_dir)
        if self.out.exists() and any(p.name != CLAIM_FILE for p in self.out.iterdir()) and not resume:
            raise FileExistsError(f"{self.out} exists and is not empty: resume it (--resume) or choose another "
                                  "output folder")
        recorded = self.out / "diagnosis.json"
        if resume and recorded.is_file():
            earlier = json.loads(recorded.read_text())
            for key, ours in (("case_dir", self.case_dir), ("fit_dir", self.fit_dir)):
                if Path(earlier[key]).resolve() != ours.resolve():
                    raise ValueError(f"{self.out} holds the diagnosis of {key.split('_')[0]} {earlier[key]}, not "
                                     f"{ours}: choose another output folder")
        self.settings = settings or DiagnosisSettings()
        self.noise = noise or NoiseModel()
        self.device = device
        self._progress = progress
        self._say = self._checked(progress)
        self._say("reading the case and the fit")
        self.fitted = load_fitted_case(case_dir, fit_dir, device=device)
        self.candidates = library(self.fitted, effects)
        base = self._fitted_solution()
        self.base_displacement = base
        self.observations = observations_of(self.fitted, base, self.noise)
        self.out.mkdir(parents=True, exist_ok=True)
        self.floor_failure: str | None = None  # why the floor could not be measured (the fixed one is used)
        self.floor = self._measured_floor(base) if self.noise.floor == "measured" else None
        if self.floor is not None:
            self.observations = self.observations.with_floor(self.floor.floor)
        self.recorder = FieldRecorder.of(self.fitted, base, registration) if registration is not None else None
        self.rounds: list[dict] = []
        self.state = ModelState(self.fitted, self.fitted.z)
        self.diagnosis: Diagnosis | None = None  # the last round's, while in memory
        self.fields: dict[tuple[int, str], ResidualField] = {}
        self.out.mkdir(parents=True, exist_ok=True)
        number = 1
        while resume and (self.out / f"round-{number}.json").is_file():
            record = json.loads((self.out / f"round-{number}.json").read_text())
            self.rounds.append(record)
            self.state = state_from_record(self.fitted, record, self.candidates)
            number += 1
        self.diagnosis = self._kept(self.last)
        if self.last is not None:  # the last round's residual fields, for its pictures and the panel's views
            for when in ("before", "after"):
                summary = (self.last.get(when) or {}).get("residual_field")
                if summary and self.path(self.last["round"], f"-residual-{when}.nrrd").is_file():
                    self.fields[(self.last["round"], when)] = ResidualField.read(
                        self.path(self.last["round"], f"-residual-{when}.nrrd"), summary.get("accuracy"))

    def _fitted_solution(self) -> np.ndarray:
        """The fitted model's solution (N, 3) mm, in every measured state (S N, 3) of a joint fit:
        the fit's deformed meshes (``states/<name>/`` of the fit folder for further states), else
        solved."""
        recorded = recorded_solution(self.fitted)
        if recorded is not None:
            return recorded
        from BreastBiomechLib.discrepancy.variants import solve_variants

        self._say("solving the fitted model")
        [outcome] = solve_variants([ModelState(self.fitted, self.fitted.z).variant()], self.fitted.mesh.nodes,
                                   self.fitted.relaxation, self.device)
        if not outcome.ok:
            raise RuntimeError(f"the fitted model does not solve ({outcome.status}: {outcome.message})")
        return outcome.displacement

    def _measured_floor(self, base: np.ndarray) -> MeasuredFloor:
        """The model-error floor measured from the case (:mod:`~BreastBiomechLib.discrepancy.floor`),
        written to floor.json; read from it where an earlier session of this folder measured it."""
        path = self.out / FLOOR_FILE
        if path.is_file():
            record = json.loads(path.read_text())
            for key, ours in (("case_dir", self.case_dir), ("fit_dir", self.fit_dir)):
                if Path(record.get(key, ours)).resolve() != ours.resolve():
                    raise ValueError(f"{self.out} holds the floor of {key.split('_')[0]} {record[key]}, not {ours}: "
                                     "choose another output folder")
            if "failed" in record:
                self.floor_failure = record["failed"]
                return None
            floor = MeasuredFloor.from_dict(record, self.noise.model_sd_mm)
            if len(floor.floor) == len(self.observations):
                return floor
        self._say("measuring the model-error floor (the fitted model solved on its refined fitting mesh)")
        regions = feature_regions(self.fitted, self.observations, base)
        where = {"case_dir": str(self.case_dir), "fit_dir": str(self.fit_dir)}
        try:
            floor = measure_floor(ModelState(self.fitted, self.fitted.z), self.observations, base, regions,
                                  self.noise.model_sd_mm)
        except RuntimeError as error:  # the refined model did not solve: said, recorded, the fixed floor used
            self.floor_failure = str(error)
            self._say(f"the model-error floor could not be measured; the fixed floor ({self.noise.model_sd_mm:g} mm) "
                      f"is used: {error}")
            write_text_atomically(path, json.dumps({"failed": self.floor_failure} | where) + "\n")
            return None
        write_text_atomically(path, json.dumps(floor.to_dict() | where) + "\n")
        return floor

    @staticmethod
    def _checked(progress):
        def say(message: str) -> None:
            if progress is not None and progress(message) is False:
                raise DiagnosisCancelled(f"cancelled while {message}")
        return say

    def _told(self, progress):
        """``progress`` for a message after a step's last write: its answer is not a Cancel (the
        step is done and on disk; a Cancel clicked during it would otherwise land here and be
        reported as "nothing was changed")."""
        progress = progress if progress is not None else self._progress

        def tell(message: str) -> None:
            if progress is not None:
                progress(message)
        return tell

    # -- what the session holds ---------------------------------------------------------------

    @property
    def rejected(self) -> set[str]:
        """The candidates turned down in any round (not tested again)."""
        return {name for r in self.rounds for name in r.get("rejected", [])}

    @property
    def added(self) -> list[str]:
        return [r["added"] for r in self.rounds if r.get("added")]

    @property
    def last(self) -> dict | None:
        return self.rounds[-1] if self.rounds else None

    def path(self, number: int, suffix: str = ".json") -> Path:
        return self.out / f"round-{number}{suffix}"

    # -- the steps ----------------------------------------------------------------------------

    def diagnose(self, progress: Callable[[str], object] | None = None) -> dict:
        """A round at the current model over the candidates not rejected (an open last round is
        replaced): the diagnosis, the measures and the residual field before any refit; written
        as round-<N>.json. Returns the round's record."""
        say = self._checked(progress) if progress is not None else self._say
        number = len(self.rounds) if self.last is not None and is_open(self.last) else len(self.rounds) + 1
        if self.last is not None and not is_open(self.last) and \
                self.last["diagnosis"]["verdict"] == "no significant discrepancy" and not self.last.get("added"):
            raise ValueError(f"round {self.last['round']} found no significant discrepancy: nothing is left to diagnose")
        started = time.perf_counter()
        key = self._round_key(number)
        diagnosis = self._checkpoint(number, key) if number > len(self.rounds) else None
        kept = diagnosis is not None  # round-<N>-kept.npz holds this round's diagnosis
        if kept:
            say(f"round {number}: its solves and statistics taken from the interrupted run's checkpoint")
        else:
            say(f"round {number}: diagnosing")
            diagnosis = diagnose(self.state, self.observations, self.candidates, self.settings,
                                 lambda m: say(f"round {number}: {m}"),
                                 excluded={name: "rejected in an earlier round" for name in self.rejected})
            if self.recorder is not None:  # the registration follows before the first write: a checkpoint
                self._keep(number, diagnosis, key)
                kept = True
        regions = diagnosis.feature_regions
        fitted, observations = self.fitted, self.observations
        record = {"round": number, "diagnosis": diagnosis.to_dict(), "state_before": self.state.to_dict(),
                  "before": measures(fitted, observations, diagnosis.sensitivities.displacement, regions),
                  "features": {"count": len(observations),
                               "channels": {c: int(np.sum(observations.channel == c))
                                            for c in sorted(set(observations.channel))},
                               "states": {name: int(np.sum(observations.in_state(name)))
                                          for name in fitted.state_names}},
                  "noise": self.noise.__dict__ | {"channels": list(self.noise.channels)},
                  "floor": self.floor.summary() if self.floor is not None else
                  {"fixed_mm": self.noise.model_sd_mm} | ({"not_measured": self.floor_failure}
                                                          if self.floor_failure else {})}
        record["refits"] = {name: measures(fitted, observations, r.displacement, regions)
                            for name, r in diagnosis.refits.items() if r.ok}
        if self.recorder is not None:
            say(f"round {number}: residual displacement field (deformable registration)")
            field_started = time.perf_counter()
            self._record_field(record, "before", diagnosis.sensitivities.displacement)
            record["residual_field_seconds"] = round(time.perf_counter() - field_started, 1)
        record["state_after"] = self.state.to_dict()
        record["seconds"] = round(time.perf_counter() - started, 1)
        self.rounds[number - 1:] = [record]
        self.diagnosis = diagnosis
        if is_open(record):  # it waits for a decision, maybe in another process: kept before the record is written
            if not kept:
                self._keep(number, diagnosis)
        else:  # a checkpoint only: gone before the record is written (a kill between costs a diagnosis, no more)
            self.path(number, KEPT).unlink(missing_ok=True)
        self._write(record)
        self._told(progress)(f"round {number}: {diagnosis.sentence}")
        return record

    def add(self, name: str, iterations: int | None = None, progress: Callable[[str], object] | None = None,
            profile: bool | None = None) -> dict:
        """Add candidate ``name`` to the model of the last round and refit (warm start: the
        round's confirmation refit, else a refit from its sensitivities), refined by
        ``iterations`` Gauss-Newton iterations (default: the settings' when the round did not
        refine it already), with its profile intervals where ``profile`` (default: the
        settings'; a diagnosis whose refinement waits for a person's decision leaves them to this
        step); the measures and the residual field after; the round's record rewritten. Needs the
        round's diagnosis in memory (diagnose it in this session)."""
        say = self._checked(progress) if progress is not None else self._say
        record, diagnosis = self._decidable()
        candidate = next((c for c in diagnosis.candidates if c.name == name), None)
        if candidate is None or candidate.skipped:
            tested = [c.name for c in diagnosis.candidates if not c.skipped]
            raise ValueError(f"{name!r} was not tested in round {record['round']}"
                             + (f" ({candidate.skipped})" if candidate is not None else "")
                             + f"; the tested candidates are {tested}")
        effect = next(e for e in self.candidates if e.name == name)
        started = time.perf_counter()
        refits = dict(diagnosis.refits)
        if diagnosis.effect == name and diagnosis.refitted is not None:
            refits[name] = diagnosis.refitted
            more = iterations or 0
        else:
            more = self.settings.refine_iterations if iterations is None else iterations
        chosen = adopt(self.state, self.observations, diagnosis.sensitivities, candidate, effect, refits, more,
                       lambda m: say(f"round {record['round']}: {m}"),
                       self.settings.profile if profile is None else profile, self.settings.min_effect)
        record["diagnosis"] = diagnosis.to_dict()
        record["added"] = name
        record["accepted"] = "verdict" if diagnosis.effect == name else "user"
        record["after"] = measures(self.fitted, self.observations, chosen.displacement, diagnosis.feature_regions)
        if self.recorder is not None:
            say(f"round {record['round']}: residual displacement field after adding {name}")
            self._record_field(record, "after", chosen.displacement)
        self.state = chosen.state
        record["state_after"] = self.state.to_dict()
        record["seconds"] = round(record.get("seconds", 0.0) + time.perf_counter() - started, 1)
        self.diagnosis = replace(diagnosis, refitted=chosen, effect=name)
        if self.path(record["round"], KEPT).is_file():  # kept with the refit: a later session shows it
            self._keep(record["round"], self.diagnosis)
        self._write(record)
        self._told(progress)(f"round {record['round']}: added {effect.title} ({effect.describe(chosen.values)})")
        return record

    def design(self, kinds=None, progress: Callable[[str], object] | None = None) -> dict:
        """The next measurement after the last round (which must be decided): for the candidates
        it could not tell apart (:func:`~BreastBiomechLib.discrepancy.design.undecided`), each
        acquisition of the library's ``kinds`` (kinds or names; default all) simulated from the
        current model and its separation from the closest rival and the fitted parameters, with
        the session's features and noise model: where the floor was measured from the case, each
        simulated acquisition's floor is measured there too (:func:`~BreastBiomechLib.discrepancy.design.design`).
        Written as design.json and design.md and
        added to the report; returns design.json's record: ``undecided`` the round's candidates it
        could not tell apart, ``designed_for`` those among the session's effects (empty, and
        nothing simulated, where there are none)."""
        from BreastBiomechLib.discrepancy.acquisitions import KINDS
        from BreastBiomechLib.discrepancy.design import Design, design, undecided, with_rivals

        say = self._checked(progress) if progress is not None else self._say
        last = self.last
        if last is None:
            raise ValueError("no round diagnosed yet: diagnose first, then design the next measurement")
        if is_open(last):
            raise ValueError(f"round {last['round']} waits for a decision ({last['diagnosis']['verdict']}): add or "
                             "reject its effect first, then design the next measurement")
        unresolved = undecided(last["diagnosis"], {e.name: e for e in library(self.fitted)})
        chosen = {e.name for e in self.candidates}
        wanted = [name for name in unresolved if name in chosen]
        record = {"round": last["round"], "undecided": unresolved, "designed_for": wanted}
        if wanted:
            say(f"designing the next measurement for {', '.join(wanted)}")
            # the diagnosis's own features and noise: its measured floor, each acquisition's measured there
            made = design(self.fitted, with_rivals(last["diagnosis"], wanted), tuple(kinds or KINDS), noise=self.noise,
                          alpha=self.settings.alpha, state=self.state, progress=say, designed_for=wanted,
                          observations=self.observations)
            record.update(made.only(wanted).to_dict())
            write_text_atomically(self.out / DESIGN_MARKDOWN, made.only(wanted).markdown())
        else:
            record.update(Design([], [], {}, self.settings.alpha, {}).to_dict())
        write_text_atomically(self.out / DESIGN_FILE, json.dumps(record, indent=1, default=float) + "\n")
        write_report(self.run(), self.out / "report.md")
        return record

    def reject(self, name: str) -> dict:
        """Turn candidate ``name`` down in the last round: it is not tested in later rounds."""
        record, diagnosis = self._decidable(need_memory=False)
        tested = [c["name"] for c in record["diagnosis"]["candidates"] if not c["skipped"]]
        if name not in tested:
            raise ValueError(f"{name!r} was not tested in round {record['round']}; the tested candidates are {tested}")
        record["rejected"] = sorted(set(record.get("rejected", [])) | {name})
        self._write(record)
        return record

    def _kept(self, record: dict | None) -> Diagnosis | None:
        """The kept diagnosis of round ``record`` (:mod:`~BreastBiomechLib.discrepancy.kept`: a round
        that waited for a decision, with its refit once decided) where its file is there and
        readable by this library; else None."""
        if record is None or not self.path(record["round"], KEPT).is_file():
            return None
        try:
            before = state_from_record(self.fitted, record, self.candidates, "before")
            return load_diagnosis(self.path(record["round"], KEPT), before, self.candidates)
        except (ValueError, KeyError) as error:
            self._say(f"round {record['round']}: its kept diagnosis is not used ({error}); diagnose it again")
            return None

    def _round_key(self, number: int) -> dict:
        """What round ``number`` is diagnosed from, as its checkpoint records it: the model (fit
        parameters, effects added), the candidates and those rejected, the settings, and a
        digest of the features (measured values and each one's sd, so the noise model and the
        floor)."""
        import hashlib

        digest = hashlib.sha256(np.ascontiguousarray(self.observations.measured, float).tobytes()
                                + np.ascontiguousarray(self.observations.sigma, float).tobytes()).hexdigest()
        return {"round": number, "state": self.state.to_dict(), "candidates": [e.name for e in self.candidates],
                "rejected": sorted(self.rejected), "settings": self.settings.__dict__, "features": digest}

    def _checkpoint(self, number: int, key: dict) -> Diagnosis | None:
        """Round ``number``'s checkpoint (kept before its first write by a run that was then
        interrupted) where it was diagnosed from ``key``; else None (and any other one removed)."""
        path = self.path(number, KEPT)
        if not path.is_file():
            return None
        try:
            return load_diagnosis(path, self.state, self.candidates, key)
        except (ValueError, KeyError) as error:
            self._say(f"round {number}: the interrupted run's checkpoint is not used ({error})")
            path.unlink(missing_ok=True)
            return None

    @staged("checkpoints")
    def _keep(self, number: int, diagnosis: Diagnosis, key: dict | None = None) -> None:
        save_diagnosis(self.path(number, KEPT), diagnosis, key)

    def _decidable(self, need_memory: bool = True) -> tuple[dict, Diagnosis | None]:
        record = self.last
        if record is None:
            raise ValueError("no round yet: diagnose first")
        if record.get("added"):
            raise ValueError(f"round {record['round']} already added {record['added']}: diagnose the next round")
        if need_memory and self.diagnosis is None:
            raise ValueError(f"round {record['round']} was diagnosed in an earlier session whose sensitivities are "
                             "not kept (an older library, or its kept file removed): diagnose again (it replaces the "
                             "open round)")
        return record, self.diagnosis

    def _record_field(self, record: dict, when: str, displacement: np.ndarray) -> None:
        """The residual field of the round's model ``when`` ("before" or "after" its refit) into
        ``record`` and beside it (.nrrd), and the round's picture (.png) of all its fields."""
        from BreastBiomechLib.discrepancy.pictures import save_residual_maps

        number = record["round"]
        field = self.recorder.field(displacement)
        self.fields[(number, when)] = field
        if when == "before":
            self.fields.pop((number, "after"), None)
        record[when]["residual_field"] = self.recorder.summary(field, displacement,
                                                               self.path(number, f"-residual-{when}.nrrd"))
        rows = [("before" if w == "before" else f"after adding {record['added']}", self.fields[(number, w)],
                 self.fields[(number, w)].landmarks) for w in ("before", "after") if (number, w) in self.fields]
        picture = save_residual_maps(self.path(number, "-residual.png"), self.fitted.measured_image, rows,
                                     title="residual displacement field (registration of the predicted to the "
                                           "measured image)")
        record["residual_picture"] = picture.name

    @staged("report")
    def _write(self, record: dict) -> None:
        from BreastBiomechLib.discrepancy.workflow import DiagnosisRun

        write_text_atomically(self.path(record["round"]), json.dumps(record, indent=1, default=float) + "\n")
        run = DiagnosisRun(self.rounds, self.out)
        write_text_atomically(self.out / "diagnosis.json", json.dumps(
            {"case_dir": str(self.case_dir), "fit_dir": str(self.fit_dir), "settings": self.settings.__dict__,
             "rounds": self.rounds, "final": run.final["verdict"], "added": run.added}, indent=1, default=float) + "\n")
        write_report(run, self.out / "report.md")

    def run(self):
        """The :class:`~BreastBiomechLib.discrepancy.workflow.DiagnosisRun` of the rounds so far."""
        from BreastBiomechLib.discrepancy.workflow import DiagnosisRun

        return DiagnosisRun(self.rounds, self.out)
