"""Whether a case's identifiability statements hold (issue 78): for each library effect a case
hides, what its first round said about seeing it (absorbed by the fitted parameters, its
smallest detectable size, "not identifiable here") against the truth's size and whether the
rounds named it. Across the suite: an effect hidden at or above the smallest size the case
reported it could detect should be named (target >= 80 %); one the case called not identifiable
should not be (target <= 20 %).

The truth's size is put in the units of the candidate's parameters (:func:`truth_sizes`); the
suite's truths are made by other code than the candidates, so for some effects this is an
equivalence, stated per effect. For a candidate of several parameters (the plate tilt's four
angles) the truth's size is compared with the smallest detectable size among them, the most
favourable axis: "at or above" is then generous, which makes the named-rate target harder to
meet, not easier.

Reads a hidden effect's truth: the suite's scoring only (never the fit or the diagnosis).
"""

from __future__ import annotations

import math

import numpy as np

from BreastBiomechLib.discrepancy import effects
from BreastBiomechLib.discrepancy.suite.cases import HiddenEffect, SuiteCase


def truth_sizes(hidden: HiddenEffect) -> dict[str, float]:
    """Each library effect ``hidden`` hides: its size away from the candidate's off value, in
    the candidate's units. friction: the truth's mu. gravity: 1 (real gravity on fat of the
    truth's 10 kPa: the candidate's s). chest-wall: the hold h = k / (k + k_ref) of the truth's
    tangential stiffness k (the candidate's springs). skin: its outer shell's (the larger):
    ln(1 + (E/E_fat - 1) min(t, d) / d) for the shell's depth d, the truth layer's excess
    membrane stiffness (E - E_fat) t in that shell spread over the shell.
    plate-tilt: the largest of the truth's angles (deg), against the candidate's angles alone.
    The refinements the truth holds (:attr:`~BreastBiomechLib.discrepancy.suite.cases.HiddenEffect.optional`):
    friction-per-plate: the largest |ln(mu_i / mu_P)|; gravity-direction: the angle (deg) between
    the truth's gravity at the compressed scan and the one its case records (the candidate's two
    angles compose to it)."""
    from BreastBiomechLib.discrepancy.effects.chest_wall import REFERENCE_STIFFNESS
    from BreastBiomechLib.discrepancy.effects.skin import SHELLS_MM
    from BreastBiomechLib.phantom.compressed import DEFAULT_TRUTH_MATERIALS

    fat = float(DEFAULT_TRUTH_MATERIALS["fat"]["E"])
    truth, sizes = hidden.truth, {}
    for name in (*hidden.expected, *hidden.optional):
        if name == "friction":  # one mu, or per plate their geometric mean (what friction per plate keeps)
            sizes[name] = float(np.exp(np.mean(np.log(np.atleast_1d(truth["friction"])))))
        elif name == "friction-per-plate":
            mu = np.atleast_1d(np.asarray(truth["friction"], float))
            sizes[name] = float(np.max(np.abs(np.log(mu[:-1] / mu[-1])))) if mu.size > 1 else 0.0
        elif name == "gravity-direction":
            turned, recorded = (np.asarray(truth[key], float) for key in ("compression_gravity", "recorded_gravity"))
            cosine = turned @ recorded / (np.linalg.norm(turned) * np.linalg.norm(recorded))
            sizes[name] = float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))
        elif name == "gravity":
            sizes[name] = 1.0
        elif name == "chest-wall":
            k = float(truth["chest_wall_stiffness"][1])
            sizes[name] = k / (k + REFERENCE_STIFFNESS)
        elif name == "skin":
            modulus, thickness = (float(v) for v in truth["skin"])
            (_, depth) = SHELLS_MM[0]
            sizes[name] = math.log(1.0 + (modulus / fat - 1.0) * min(thickness, depth) / depth)
        elif name == "plate-tilt":
            sizes[name] = max(abs(float(a)) for plate in truth["plate_tilt_deg"] for a in plate)
    return sizes


def _candidate(record: dict, name: str) -> dict | None:
    return next((c for c in record["diagnosis"].get("candidates", []) if c.get("name") == name), None)


def not_identifiable(candidate: dict, name: str) -> bool:
    """Whether a round said of ``candidate`` (a round record's candidate of the library effect
    ``name``) that this case could not have shown it
    (:func:`~BreastBiomechLib.discrepancy.diagnosis.not_identifiable`)."""
    from BreastBiomechLib.discrepancy import diagnosis  # SimpleITK, SciPy

    detectable = candidate.get("detectable") or []
    made = {"friction": effects.PlateFriction, "gravity": effects.GravityPrestress, "chest-wall": effects.ChestWallHold,
            "friction-per-plate": lambda: effects.FrictionPerPlate(len(detectable) + 1),
            "gravity-direction": effects.GravityDirection,
            # every plate parameter reaches 5 (deg or mm) either way: enough of them, in any order, say the same
            "skin": effects.SkinLayer, "plate-tilt": lambda: effects.PlateTilt(max(len(detectable), 1))}
    return diagnosis.not_identifiable(candidate, made[name]() if name in made else None)


def _parameters(candidate: dict) -> list[str]:
    """The names of a candidate record's parameters ("" each where an older record has none)."""
    return candidate.get("parameters") or [""] * len(candidate.get("detectable") or [])


def _in_truth_units(name: str, parameter: str) -> bool:
    """Whether candidate ``name``'s parameter ``parameter`` is in the units :func:`truth_sizes`
    gives its size in: the plate tilt's angles, not the offsets its pose moves with."""
    return name != "plate-tilt" or ".offset" not in parameter


def identifiability(case: SuiteCase, rounds: list[dict]) -> dict:
    """Per library effect the case hides (with a size, :func:`truth_sizes`), what the first round
    that tested it said (the first round for all but a refinement, which is tested once the
    effect it refines was added): {name: {"size", "detectable" (the smallest of its parameters';
    None: none), "absorbed", "not_identifiable", "at_or_above_detectable" (identifiable and the
    size at least the detectable one: the two are never both true), "named" (some round added
    it)}}; an effect no round tested (skipped, not chosen) is left out."""
    added = {r["added"] for r in rounds if r.get("added")}
    out = {}
    for name, size in truth_sizes(case.hidden).items():
        candidate = next((c for c in (_candidate(r, name) for r in rounds) if c is not None and not c.get("skipped")),
                         None)
        if candidate is None:
            continue
        sizes = [d for d, parameter in zip(candidate.get("detectable") or [], _parameters(candidate))
                 if d is not None and _in_truth_units(name, parameter)]
        smallest = min(sizes) if sizes else None
        hidden = not_identifiable(candidate, name)
        out[name] = {"size": size, "detectable": smallest, "absorbed": candidate.get("absorbed"),
                     "not_identifiable": hidden,
                     "at_or_above_detectable": not hidden and smallest is not None and size >= smallest,
                     "named": name in added}
    return out


def told_absorbed_by_muscle(record: dict, name: str) -> bool:
    """Whether round ``record`` said candidate ``name`` is not identifiable here and that the
    fitted pectoral muscle's parameters take it up (issue 78's rule for a one-scan chest-wall
    case: right when the verdict says so): not identifiable (its signature reproduced at least
    :data:`~BreastBiomechLib.discrepancy.diagnosis.ABSORBED` by the fitted parameters, or its
    smallest detectable size beyond its range), the larger part of it (at least
    :data:`~BreastBiomechLib.discrepancy.diagnosis.TAKEN_UP`) reproduced, chiefly by a muscle
    parameter - what the verdict then says of it."""
    from BreastBiomechLib.discrepancy.diagnosis import TAKEN_UP

    candidate = _candidate(record, name)
    return (candidate is not None and not candidate.get("skipped") and not_identifiable(candidate, name)
            and candidate.get("absorbed", float("nan")) >= TAKEN_UP
            and str((candidate.get("absorbed_by") or {}).get("name", "")).startswith("muscle."))


def calibration(results: list[dict]) -> dict:
    """Across the finished cases: {"at_or_above_detectable": [named, cases], "not_identifiable":
    [named, cases], "by_effect": {name: the same two pairs}}."""
    out = {"at_or_above_detectable": [0, 0], "not_identifiable": [0, 0], "by_effect": {}}
    for r in results:
        for name, row in (r.get("identifiability") or {}).items():
            per = out["by_effect"].setdefault(name, {"at_or_above_detectable": [0, 0], "not_identifiable": [0, 0]})
            for key in ("at_or_above_detectable", "not_identifiable"):
                if row[key]:
                    for cell in (out[key], per[key]):
                        cell[0] += int(row["named"])
                        cell[1] += 1
    return out
