"""The whole workflow on a fitted case: diagnose, add the named effect with its refit, and repeat
until nothing significant remains (or ``rounds`` are done), writing each round as it finishes so
that an interrupted run resumes.

Output folder::

    round-<N>.json   each round: the diagnosis (verdict, every statistic), the model before and
                     after (fit parameters, effects added), landmark error, NMI and residual by
                     region before and after the refit
    diagnosis.json   all rounds and the final verdict
    round-<N>-residual-{before,after}.nrrd
                     the residual displacement field of the round's model before and after its refit
                     (vector, LPS mm, on the measured image's grid; Slicer loads it as a vector
                     volume; it is a residual, measured minus model position, not a resampling transform)
    round-<N>-residual.png
                     its magnitude over the measured image, before and after, with the landmark residuals
    report.md        the report (:mod:`BreastBiomechLib.discrepancy.report`)
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from BreastBiomechLib.discrepancy.diagnosis import DiagnosisSettings, diagnose, region_summary
from BreastBiomechLib.discrepancy.effects import library
from BreastBiomechLib.discrepancy.fitted import FittedCase, load_fitted_case
from BreastBiomechLib.discrepancy.observations import NoiseModel, Observations, observations_of
from BreastBiomechLib.discrepancy.registration import RegistrationSettings, ResidualField
from BreastBiomechLib.discrepancy.state import ModelState


def write_atomically(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file renamed over it: never half written."""
    temporary = path.with_name(path.name + ".partial")
    temporary.write_text(text)
    os.replace(temporary, path)


def measures(fitted: FittedCase, observations: Observations, displacement: np.ndarray, regions) -> dict:
    """What the report compares before and after a round: landmark errors (mm), NMI against the
    measured image, and the residual by region."""
    out = {}
    if fitted.reference is not None:
        from BreastBiomechLib.landmarks import map_landmarks

        moved = map_landmarks(fitted.mesh, displacement, fitted.reference)
        errors = np.linalg.norm(moved.positions - fitted.measured.positions, axis=1)
        out["landmark_error_mm"] = {"mean": float(errors.mean()), "max": float(errors.max()),
                                    "per_landmark": dict(zip(fitted.reference.labels, errors.round(3).tolist()))}
    out["nmi"] = float(fitted.problem.similarity.nmi(fitted.problem.warper.warp(displacement)))
    residual = observations.residual(displacement)
    out["residual_rms_mm"] = float(np.sqrt(np.mean(residual ** 2)))
    out["regions"] = region_summary(observations, residual, regions)
    return out


@dataclass
class FieldRecorder:
    """Makes, summarises and saves the residual displacement fields of a run's models (see
    :mod:`~BreastBiomechLib.discrepancy.registration`): the measured body found once, the
    fitting mesh's nodes labelled by region once."""

    fitted: FittedCase
    settings: RegistrationSettings
    node_regions: np.ndarray
    body: np.ndarray

    @classmethod
    def of(cls, fitted: FittedCase, base_displacement: np.ndarray, settings: RegistrationSettings) -> FieldRecorder:
        import SimpleITK as sitk

        from BreastBiomechLib.discrepancy.regions import regions_of
        from BreastBiomechLib.segmentation.body import body_mask
        from BreastBiomechLib.segmentation.volume import check_volume

        body = body_mask(sitk.GetArrayFromImage(fitted.measured_image).astype(np.float32),
                         check_volume(fitted.measured_image))
        return cls(fitted, settings, regions_of(fitted, fitted.mesh.nodes, base_displacement), body)

    def field(self, displacement: np.ndarray) -> ResidualField:
        from BreastBiomechLib.discrepancy.registration import residual_field_of

        return residual_field_of(self.fitted, displacement, self.body, self.settings)

    def summary(self, field: ResidualField, displacement: np.ndarray, path: Path) -> dict:
        """The figures of ``field`` (of the model whose solution is ``displacement``), saved to ``path``."""
        import SimpleITK as sitk

        from BreastBiomechLib.discrepancy.registration import field_by_region

        image = sitk.Cast(field.image(), sitk.sitkVectorFloat32)
        sitk.WriteImage(image, str(path.with_name(path.name + ".partial.nrrd")), useCompression=True)
        os.replace(path.with_name(path.name + ".partial.nrrd"), path)
        magnitude = field.magnitude[field.mask]
        return {"file": path.name, "mean_mm": float(magnitude.mean()), "p95_mm": float(np.percentile(magnitude, 95)),
                "accuracy": field.accuracy,
                "regions": field_by_region(field, self.fitted.mesh.nodes, displacement, self.node_regions)}


def state_from_record(fitted: FittedCase, record: dict, effects) -> ModelState:
    """The model after a recorded round."""
    by_name = {e.name: e for e in effects}
    after = record["state_after"]
    state = ModelState(fitted, np.asarray(after["z"], float))
    for name, values in after["added"].items():
        state = state.with_effect(by_name[name], values)
    return state


def record_fields(recorder: FieldRecorder, record: dict, diagnosis, stem: Path) -> None:
    """The residual fields of a round's model before (and after, when an effect was added) into
    ``record`` and beside ``stem``: the fields (.nrrd) and their picture (.png)."""
    from BreastBiomechLib.discrepancy.pictures import save_residual_maps

    fitted = recorder.fitted
    rows = []
    for when, displacement in (("before", diagnosis.sensitivities.displacement),
                               ("after", diagnosis.refitted.displacement if diagnosis.refitted is not None else None)):
        if displacement is None:
            continue
        field = recorder.field(displacement)
        record[when]["residual_field"] = recorder.summary(field, displacement,
                                                          stem.with_name(f"{stem.name}-residual-{when}.nrrd"))
        rows.append((when if when == "before" else f"after adding {record['added']}", field, field.landmarks))
    picture = save_residual_maps(stem.with_name(f"{stem.name}-residual.png"), fitted.measured_image, rows,
                                 title="residual displacement field (registration of the predicted to the measured image)")
    record["residual_picture"] = picture.name


@dataclass
class DiagnosisRun:
    """A finished workflow: every round's record, the final verdict's round and the folder."""

    rounds: list[dict]
    folder: Path

    @property
    def final(self) -> dict:
        return self.rounds[-1]["diagnosis"]

    @property
    def added(self) -> list[str]:
        return [r["added"] for r in self.rounds if r.get("added")]


def run_diagnosis(case_dir, fit_dir, out_dir, effects=None, rounds: int = 3, noise: NoiseModel | None = None,
                  settings: DiagnosisSettings | None = None, device=None, resume: bool = False,
                  progress: Callable[[str], None] | None = None,
                  registration: RegistrationSettings | None = RegistrationSettings()) -> DiagnosisRun:
    """Diagnose the fit in ``fit_dir`` of the compressed case in ``case_dir`` over the candidate
    ``effects`` (names; default the whole library) for at most ``rounds`` rounds, writing to
    ``out_dir`` (a new folder, or the folder of an interrupted run with ``resume``). Each round's
    models are also compared through the residual displacement field of a deformable
    registration (``registration``; None: not made)."""
    from BreastBiomechLib.discrepancy.report import write_report
    from BreastBiomechLib.io.meshes import read_vtu

    say = progress or (lambda message: None)
    if rounds < 1:
        raise ValueError("the diagnosis needs at least one round")
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()) and not resume:
        raise FileExistsError(f"{out} exists and is not empty: resume it (--resume) or choose another output folder")
    out.mkdir(parents=True, exist_ok=True)
    settings = settings or DiagnosisSettings()
    noise = noise or NoiseModel()
    say("reading the case and the fit")
    fitted = load_fitted_case(case_dir, fit_dir, device=device)
    candidates = library(fitted, effects)
    fitted_solution = Path(fit_dir) / "deformed_mesh.vtu"
    if fitted_solution.is_file():
        base = read_vtu(fitted_solution).point_data["displacement"]
    else:
        from BreastBiomechLib.discrepancy.variants import solve_variants

        base = solve_variants([ModelState(fitted, fitted.z).variant()], fitted.mesh.nodes, fitted.relaxation,
                              device)[0].displacement
    observations = observations_of(fitted, base, noise)
    state = ModelState(fitted, fitted.z)
    recorder = FieldRecorder.of(fitted, base, registration) if registration is not None else None
    records = []
    for number in range(1, rounds + 1):
        path = out / f"round-{number}.json"
        if resume and path.is_file():
            record = json.loads(path.read_text())
            records.append(record)
            say(f"round {number}: {record['diagnosis']['verdict']} (from {path})")
            if not record.get("added"):
                break
            state = state_from_record(fitted, record, candidates)
            continue
        started = time.perf_counter()
        say(f"round {number}: diagnosing")
        diagnosis = diagnose(state, observations, candidates, settings, lambda m: say(f"round {number}: {m}"))
        regions = diagnosis.feature_regions
        record = {"round": number, "diagnosis": diagnosis.to_dict(), "state_before": state.to_dict(),
                  "before": measures(fitted, observations, diagnosis.sensitivities.displacement, regions),
                  "features": {"count": len(observations), "channels": {c: int(np.sum(observations.channel == c))
                                                                        for c in sorted(set(observations.channel))}},
                  "noise": noise.__dict__ | {"channels": list(noise.channels)}}
        record["refits"] = {name: measures(fitted, observations, r.displacement, regions)
                            for name, r in diagnosis.refits.items() if r.ok}
        if diagnosis.refitted is not None:
            state = diagnosis.refitted.state
            record["added"] = diagnosis.effect
            record["after"] = measures(fitted, observations, diagnosis.refitted.displacement, regions)
        if recorder is not None:
            say(f"round {number}: residual displacement field (deformable registration)")
            field_started = time.perf_counter()
            record_fields(recorder, record, diagnosis, out / f"round-{number}")
            record["residual_field_seconds"] = round(time.perf_counter() - field_started, 1)
        record["state_after"] = state.to_dict()
        record["seconds"] = round(time.perf_counter() - started, 1)
        write_atomically(path, json.dumps(record, indent=1, default=float) + "\n")
        records.append(record)
        say(f"round {number}: {diagnosis.sentence}")
        if diagnosis.refitted is None:
            break
    run = DiagnosisRun(records, out)
    write_atomically(out / "diagnosis.json", json.dumps({"case_dir": str(case_dir), "fit_dir": str(fit_dir),
                                                         "settings": settings.__dict__, "rounds": records,
                                                         "final": run.final["verdict"], "added": run.added},
                                                        indent=1, default=float) + "\n")
    write_report(run, out / "report.md")
    return run
