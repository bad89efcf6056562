"""A round's diagnosis kept on disk beside its record, so that another process (or a later
session) decides on it: adds a candidate and refits from the round's sensitivities and refits,
or shows a candidate's predicted residual, without diagnosing the round again. The Breast
Discrepancy panel diagnoses in one process (`breastbiomech diagnose --one-round`) and adds
the effect the user accepts in another (`--add NAME`). Kept also as a round's checkpoint, before
its first write, with the ``key`` of what it was diagnosed from: a run interrupted before the
round is written takes its solves and statistics up again instead of making them anew.

``round-<N>-kept.npz`` holds the arrays (the sensitivities, the refits' values, displacements
and residuals, each feature's region) and one JSON document (``meta``) with the rest: the
verdict and its evidence (as in the round's record), the refits' figures, the refitted states
(fit parameters and added effects) and the library version. Written atomically; read only by
the same library version (another one diagnoses the round again). Units as in the diagnosis:
mm, displacements LPS.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np

from BreastBiomechLib import __version__
from BreastBiomechLib.discrepancy.diagnosis import Candidate, Diagnosis
from BreastBiomechLib.discrepancy.refit import Refit
from BreastBiomechLib.discrepancy.sensitivity import Sensitivities
from BreastBiomechLib.discrepancy.state import ModelState

SUFFIX = "-kept.npz"
FORMAT = 3  # 2: the prior-data conflicts kept with the diagnosis; 3: the checkpoint's key


def _state_record(state: ModelState) -> dict:
    return {"z": [float(v) for v in state.z],
            "added": [[name, [float(v) for v in values]] for name, (_, values) in state.added.items()]}


def _state(record: dict, base: ModelState, effects: dict) -> ModelState:
    state = ModelState(base.fitted, np.asarray(record["z"], float))
    for name, values in record["added"]:
        if name not in effects:
            raise ValueError(f"the kept round added {name!r}, which this session's library does not hold")
        state = state.with_effect(effects[name], values)
    return state


def _refit_record(key: str, refit: Refit, arrays: dict) -> dict:
    for name in ("values", "sd", "displacement", "residual_after"):
        arrays[f"refit.{key}.{name}"] = np.asarray(getattr(refit, name), float)
    return {"effect": None if refit.effect is None else refit.effect.name, "state": _state_record(refit.state),
            "rss_before": refit.rss_before, "rss_after": refit.rss_after, "rss_linear": refit.rss_linear,
            "status": refit.status, "note": refit.note, "profile": refit.profile}


def _refit(key: str, record: dict, arrays, base: ModelState, effects: dict) -> Refit:
    effect = None if record["effect"] is None else effects[record["effect"]]
    return Refit(effect, arrays[f"refit.{key}.values"], arrays[f"refit.{key}.sd"], _state(record["state"], base, effects),
                 float(record["rss_before"]), float(record["rss_after"]), float(record["rss_linear"]),
                 arrays[f"refit.{key}.displacement"], arrays[f"refit.{key}.residual_after"], record["status"],
                 record["note"], record.get("profile"))


def save_diagnosis(path: str | Path, diagnosis: Diagnosis, key: dict | None = None) -> Path:
    """Keep ``diagnosis`` in ``path`` (a round-<N>-kept.npz), atomically; ``key``: what the round
    was diagnosed from (:meth:`~BreastBiomechLib.discrepancy.session.DiagnosisSession` writes it
    with a checkpoint, and takes the checkpoint up only where its own key is the same)."""
    path = Path(path)
    s = diagnosis.sensitivities
    arrays = {"feature_regions": np.asarray(diagnosis.feature_regions).astype(str),
              "sens.displacement": s.displacement, "sens.features": s.features, "sens.nuisance": s.nuisance}
    for group in ("effects", "fields", "steps"):
        for name, values in getattr(s, group).items():
            arrays[f"sens.{group}.{name}"] = np.asarray(values, float)
    refits = {name: _refit_record(name, r, arrays) for name, r in diagnosis.refits.items()}
    refitted = None if diagnosis.refitted is None else _refit_record("@refitted", diagnosis.refitted, arrays)
    meta = {"format": FORMAT, "version": __version__,
            "diagnosis": {"verdict": diagnosis.verdict, "effect": diagnosis.effect,
                          "alternatives": diagnosis.alternatives, "sentence": diagnosis.sentence,
                          "overall": diagnosis.overall, "regions": diagnosis.regions,
                          "correlations": diagnosis.correlations, "held": diagnosis.held, "edges": diagnosis.edges,
                          "prior_conflicts": diagnosis.conflicts,
                          "candidates": [c.to_dict() for c in diagnosis.candidates]},
            "sensitivities": {"nuisance_keys": s.nuisance_keys, "skipped": s.skipped, "solves": s.solves,
                              "effects": list(s.effects), "fields": list(s.fields), "steps": list(s.steps)},
            "refits": refits, "refitted": refitted, "key": key}
    arrays["meta"] = np.array(json.dumps(meta, default=float))
    handle, temporary = tempfile.mkstemp(prefix=path.name, suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(handle, "wb") as file:  # uncompressed: solutions in floats compress by ~6 % at 20x the time
            np.savez(file, **arrays)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return path


def load_diagnosis(path: str | Path, base: ModelState, effects, key: dict | None = None) -> Diagnosis:
    """The diagnosis kept in ``path`` by :func:`save_diagnosis`, for the round whose model was
    ``base`` (its state before) with the library's ``effects``. Raises ValueError where it was
    kept by another library version, names an effect the library does not hold, or (with
    ``key``) was diagnosed from anything else than ``key`` says."""
    path = Path(path)
    with np.load(path, allow_pickle=False) as data:
        arrays = {name: data[name] for name in data.files}
    meta = json.loads(str(arrays.pop("meta")))
    if meta.get("format") != FORMAT or meta.get("version") != __version__:
        raise ValueError(f"{path} was kept by BreastBiomech {meta.get('version')}, this is {__version__}: "
                         "diagnose the round again")
    if key is not None and meta.get("key") != json.loads(json.dumps(key, default=float)):
        raise ValueError(f"{path} was diagnosed from another model, candidates, settings or features")
    by_name = {e.name: e for e in effects}
    s = meta["sensitivities"]
    sensitivities = Sensitivities(
        arrays["sens.displacement"], arrays["sens.features"], list(s["nuisance_keys"]), arrays["sens.nuisance"],
        {name: arrays[f"sens.effects.{name}"] for name in s["effects"]},
        {name: arrays[f"sens.fields.{name}"] for name in s["fields"]},
        {name: arrays[f"sens.steps.{name}"] for name in s["steps"]}, dict(s["skipped"]), int(s["solves"]))
    refits = {name: _refit(name, record, arrays, base, by_name) for name, record in meta["refits"].items()}
    refitted = None if meta["refitted"] is None else _refit("@refitted", meta["refitted"], arrays, base, by_name)
    d = meta["diagnosis"]
    return Diagnosis(d["verdict"], d["effect"], list(d["alternatives"]), d["sentence"], d["overall"],
                     [Candidate(**c) for c in d["candidates"]], d["regions"], d["correlations"], refitted,
                     sensitivities, arrays["feature_regions"], refits, list(d["held"]), list(d["edges"]),
                     list(d["prior_conflicts"]))
