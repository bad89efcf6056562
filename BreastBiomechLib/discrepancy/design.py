"""The next measurement (``breastbiomech design``): which further acquisition of the breast would
tell each candidate effect apart from what takes it up at this fit.

Each acquisition of a library is simulated from the fit: the fitted model compressed another way
on the fitting mesh - the plates closing 10 or 20 % of the breast's thickness further or less,
the plates' travel moved to one plate, the plates turned 90 degrees about the breast (LR and SI
swapped) - and its predicted image (on a grid covering the compressed breast, at the measured
image's spacing) and landmarks taken as that state's measurement. For a candidate effect at its
realistic size (each parameter's sensitivity step, :class:`~BreastBiomechLib.discrepancy.
effects.EffectParameter`) the **separation** is the length, in units of the noise model's sigma,
of its signature (the features' change) beyond the span of the fitted parameters' and its closest
rival's signatures: what is left of the effect once the rival model is refitted to it, i.e. the
square root of the score test's noncentrality, T-optimality's criterion for two rival linear
models (Atkinson and Fedorov 1975). It is computed over the measured states (now) and over them
with the simulated acquisition stacked (the fit's parameters shared by every state, as in a joint
fit); a separation at or above the noncentrality at which the diagnosis's test reaches its level
with 80 % power (:func:`~BreastBiomechLib.discrepancy.statistics.detectable_noncentrality`) tells
the effect apart. Adding a state never lowers a separation.

The closest rival of an effect is the other candidate whose signature, beyond the fitted
parameters, is most nearly parallel to it (none where it is the only candidate tested); the
fitted parameters themselves are always rivals (an effect they absorb has no separation).

Linear: the signatures are the secants at this fit, except that each designed effect's best
acquisitions are checked by refitting the fitted parameters to the data the effect would make
(:mod:`~BreastBiomechLib.discrepancy.design_check`: a fitted modulus may take up more of it than
its linear step says); the noise the diagnosis's: where it measured
the model-error floor from the case, each simulated acquisition's floor is measured too (one
refined solve each), else the fixed floor
(:class:`~BreastBiomechLib.discrepancy.observations.NoiseModel`). Not in the library yet: a
posture change (the gravity model's reference state in the new posture) and a measured plate
force (the diagnosis has no force channel).

Frames and units: LPS millimetres; separations in sigma.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk

from BreastBiomechLib.discrepancy.acquisitions import KINDS, Acquisition, acquisition_library, half_push
from BreastBiomechLib.discrepancy.effects import library
from BreastBiomechLib.discrepancy.fitted import FittedCase, recorded_solution
from BreastBiomechLib.discrepancy.observations import NoiseModel, Observations, observations_of
from BreastBiomechLib.discrepancy.sensitivity import UNSOLVED, Sensitivities, sensitivities
from BreastBiomechLib.discrepancy.state import ModelState
from BreastBiomechLib.discrepancy.statistics import detectable_noncentrality
from BreastBiomechLib.io.case_layout import CaseLayout
from BreastBiomechLib.io.images import read_image

GRID_MARGIN_MM = 10.0  # around the compressed breast, of a simulated acquisition's image
POWER = 0.8  # of the detectable separation
CHECKED = 2  # acquisitions per designed effect whose separation is checked by refitting (design_check)


def covering_grid(points_mm: np.ndarray, spacing_mm, margin_mm: float = GRID_MARGIN_MM) -> sitk.Image:
    """An empty image (LPS, identity direction) at ``spacing_mm`` covering ``points_mm`` (N, 3)
    with ``margin_mm`` around them: the grid a simulated acquisition is imaged on."""
    spacing = np.asarray(spacing_mm, float)
    low = points_mm.min(axis=0) - margin_mm
    size = np.ceil((points_mm.max(axis=0) + margin_mm - low) / spacing).astype(int) + 1
    grid = sitk.Image([int(s) for s in size], sitk.sitkFloat32)
    grid.SetSpacing([float(s) for s in spacing])
    grid.SetOrigin([float(v) for v in low])
    return grid


def placed_case(fitted: FittedCase, acquisition: Acquisition, undeformed: sitk.Image, z: np.ndarray) -> FittedCase:
    """The fitted case at the parameters ``z`` with ``acquisition``'s plates on its mesh (its
    measured image still the fit's, no landmarks): the model whose solve
    :func:`simulated_measurement` images. ``undeformed``: the case's undeformed MR."""
    return _with_plates(fitted, acquisition, undeformed, z, fitted.measured_image, None)


def simulated_measurement(fitted: FittedCase, acquisition: Acquisition, undeformed: sitk.Image, z: np.ndarray,
                          displacement_mm: np.ndarray) -> FittedCase:
    """The measured state ``acquisition`` would give where the fitted model's solution with its
    plates (:func:`placed_case`) is ``displacement_mm`` (N, 3): ``undeformed`` warped through it
    onto a grid covering the compressed breast at the measured image's spacing, and the fit's
    reference landmarks mapped through it, taken as that state's measurement."""
    from BreastBiomechLib.landmarks import map_landmarks
    from BreastBiomechLib.warping import ImageWarper

    grid = covering_grid(fitted.mesh.nodes + displacement_mm, fitted.measured_image.GetSpacing())
    predicted = ImageWarper(fitted.mesh, undeformed, grid, device=fitted.device).predict(displacement_mm).image
    landmarks = (map_landmarks(fitted.mesh, displacement_mm, fitted.reference)
                 if fitted.reference is not None else None)
    return _with_plates(fitted, acquisition, undeformed, z, predicted, landmarks)


def _with_plates(fitted: FittedCase, acquisition: Acquisition, undeformed: sitk.Image, z: np.ndarray,
                 measured_image: sitk.Image, landmarks) -> FittedCase:
    """``fitted`` at ``z`` with ``acquisition``'s plates and ``measured_image`` and ``landmarks``
    (None: none) as its measurement."""
    from BreastBiomechLib.optimisation.forward import FittingProblem

    planes = [dict(p) for p in acquisition.planes]
    problem = FittingProblem(fitted.space, fitted.mesh, undeformed, measured_image, planes,
                             landmarks=(fitted.reference, landmarks) if landmarks is not None else None,
                             relaxation=fitted.relaxation, device=fitted.device)
    made = FittedCase(problem, z, fitted.reference if landmarks is not None else None, landmarks,
                      measured_image, fitted.case_dir, fitted.fit_dir, fitted.imaged_gravity,
                      fitted.compressed_gravity, fitted.relaxation, fitted.device, acquisition.name)
    made._skin = fitted._skin  # one mesh: each element's skin share is computed once
    return made


def last_round_state(fitted: FittedCase, folder) -> ModelState:
    """The model the last round of the diagnosis in ``folder`` (``breastbiomech diagnose --out``)
    ended with: the fit's parameters as refitted and the effects added. Refuses a folder that
    holds no round, or the diagnosis of another case or fit."""
    import json
    from pathlib import Path

    from BreastBiomechLib.discrepancy.session import state_from_record

    folder = Path(folder)
    rounds = sorted(folder.glob("round-*.json"), key=lambda p: int(p.stem.split("-")[1]))
    if not rounds:
        raise FileNotFoundError(f"{folder}: no diagnosis round (round-1.json); run `breastbiomech diagnose` first")
    summary = folder / "diagnosis.json"
    if summary.is_file():
        recorded = json.loads(summary.read_text())
        for key, ours in (("case_dir", fitted.case_dir), ("fit_dir", fitted.fit_dir)):
            if key in recorded and Path(recorded[key]).resolve() != Path(ours).resolve():
                raise ValueError(f"{folder} is the diagnosis of {key.split('_')[0]} {recorded[key]}, not {ours}")
    return state_from_record(fitted, json.loads(rounds[-1].read_text()), library(fitted))


def beyond(signature: np.ndarray, rivals: np.ndarray) -> np.ndarray:
    """(I - P) signature: what is left of ``signature`` (n,) beyond the span of the columns of
    ``rivals`` (n, m) (least squares; ``m`` may be 0)."""
    if rivals.size == 0:
        return signature
    coefficients, *_ = np.linalg.lstsq(rivals, signature, rcond=None)
    return signature - rivals @ coefficients


def residual_norm(signature: np.ndarray, rivals: np.ndarray) -> float:
    """|| (I - P) signature ||: the length of ``signature`` beyond the span of ``rivals`` (:func:`beyond`)."""
    return float(np.linalg.norm(beyond(signature, rivals)))


@dataclass
class Rows:
    """Whitened sensitivity rows of one or more measured states: ``nuisance`` {key: (n,)} per
    fitted parameter, ``effects`` {name: (n,)} each candidate's signature at its realistic size,
    both divided by the features' sigma; ``skipped`` {name: reason}."""

    nuisance: dict[str, np.ndarray]
    effects: dict[str, np.ndarray]
    skipped: dict[str, str] = field(default_factory=dict)
    n: int = 0

    @classmethod
    def of(cls, sens: Sensitivities, observations: Observations) -> "Rows":
        weights = 1.0 / observations.sigma
        nuisance = {key: weights * sens.nuisance[:, j] for j, key in enumerate(sens.nuisance_keys)}
        effects = {name: weights * (values @ sens.steps[name]) for name, values in sens.effects.items()}
        return cls(nuisance, effects, dict(sens.skipped), len(weights))

    def stacked(self, other: "Rows") -> "Rows":
        """These rows with ``other``'s below (a fitted parameter one state lacks: zero there)."""
        keys = list(dict.fromkeys([*self.nuisance, *other.nuisance]))
        zero_self, zero_other = np.zeros(self.n), np.zeros(other.n)
        nuisance = {k: np.concatenate([self.nuisance.get(k, zero_self), other.nuisance.get(k, zero_other)]) for k in keys}
        effects = {k: np.concatenate([v, other.effects[k]]) for k, v in self.effects.items() if k in other.effects}
        skipped = {**other.skipped, **self.skipped}
        return Rows(nuisance, effects, skipped, self.n + other.n)

    def fitted_span(self) -> np.ndarray:
        return np.column_stack(list(self.nuisance.values())) if self.nuisance else np.zeros((self.n, 0))

    def separation(self, effect: str, rival: str | None) -> float:
        """The separation (sigma) of ``effect`` beyond the fitted parameters and ``rival``."""
        span = self.fitted_span()
        if rival is not None:
            span = np.column_stack([span, self.effects[rival]])
        return residual_norm(self.effects[effect], span)

    def closest_rival(self, effect: str) -> str | None:
        """The other candidate whose signature beyond the fitted parameters is most nearly
        parallel to ``effect``'s (None: no other)."""
        span = self.fitted_span()
        mine = beyond(self.effects[effect], span)
        best, rival = -1.0, None
        for name, values in self.effects.items():
            if name == effect:
                continue
            other = beyond(values, span)
            norm = np.linalg.norm(mine) * np.linalg.norm(other)
            cosine = abs(float(mine @ other)) / norm if norm > 0 else 0.0
            if cosine > best:
                best, rival = cosine, name
        return rival


@dataclass
class Design:
    """Each candidate's separations now and with each acquisition (``effects``: one record per
    candidate, its acquisitions best first, with the separation it needs), the acquisitions
    simulated and those that could not be (``failed`` {name: why}), the diagnosis level, the
    noise model and the ``model`` designed from (:meth:`ModelState.to_dict`)."""

    effects: list[dict]
    acquisitions: list[dict]
    failed: dict[str, str]
    alpha: float
    noise: dict
    model: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"effects": self.effects, "acquisitions": self.acquisitions, "failed": self.failed, "alpha": self.alpha,
                "power": POWER, "noise": self.noise, "model": self.model}

    @classmethod
    def from_dict(cls, record: dict) -> "Design":
        """The design :meth:`to_dict` wrote (other keys are ignored)."""
        return cls(record["effects"], record["acquisitions"], record["failed"], record["alpha"], record["noise"],
                   record.get("model", {}))

    def only(self, names) -> "Design":
        """This design's records of the effects ``names`` only (their rivals were designed with them)."""
        names = set(names)
        return Design([r for r in self.effects if r["effect"] in names], self.acquisitions, self.failed, self.alpha,
                      self.noise, self.model)

    def choice(self) -> str | None:
        """The one acquisition this design recommends: the simulated acquisition that tells the
        most of its candidates apart (separation at least the detectable one) among those not told
        apart already, ties broken by the larger sum of their separations; None where none was
        simulated."""
        open_ = [r for r in self.effects if not r.get("skipped") and r["now_sigma"] < r["detectable_sigma"]]
        scored = []
        for a in self.acquisitions:
            seen = [next((x["separation_sigma"] for x in r["acquisitions"] if x["name"] == a["name"]), 0.0)
                    for r in open_]
            told = sum(s >= r["detectable_sigma"] for s, r in zip(seen, open_))
            scored.append((told, sum(seen), a["name"]))
        return max(scored)[2] if scored else None

    def markdown(self) -> str:
        """The design as a report section: the sentences, then every candidate's separation
        (sigma) now and with each acquisition."""
        names = [a["name"] for a in self.acquisitions]
        lines = ["## The next measurement", "",
                 "Separation of each candidate effect at its realistic size from its closest rival and the fitted "
                 "parameters, in sigma of the noise model (landmarks "
                 f"{self.noise['landmark_sd_mm']} mm, model floor {self.noise['model_sd_mm']} mm), now and with each "
                 f"simulated acquisition added; told apart at the detectable separation (level {self.alpha}, "
                 f"{100 * POWER:.0f} % power).", ""]
        lines += [f"- {sentence}" for sentence in self.sentences()] + [""]
        lines += ["| effect | rival | needed | now | " + " | ".join(names) + " |",
                  "|---|---|---|---|" + "---|" * len(names)]
        for record in self.effects:
            seen = {a["name"]: a["separation_sigma"] for a in record["acquisitions"]}
            cells = [f"{seen[n]:.1f}" if n in seen else "not solved" for n in names]
            lines.append(f"| {record['title']} | {record.get('rival_title') or '-'} | {record['detectable_sigma']:.1f} | "
                         f"{record['now_sigma']:.1f} | " + " | ".join(cells) + " |")
        lines += ["", *[f"- {a['name']}: {a['description']}" + "".join(
            f"; {effect} not solved there ({why})" for effect, why in a["skipped"].items()) for a in self.acquisitions]]
        lines += [f"- {name}: not simulated ({why})" for name, why in self.failed.items()]
        lines += [f"- {a['name']} for {record['title']}: {a['linear_sigma']:.1f} sigma by the linearisation, "
                  + (f"{a['separation_sigma']:.1f} with the fitted parameters refitted to what it would show "
                     f"({_moved_words(a['refitted']['moved'])})" if "failed" not in a["refitted"]
                     else f"not checked ({a['refitted']['failed']})")
                  for record in self.effects for a in record.get("acquisitions", []) if "linear_sigma" in a]
        return "\n".join(lines) + "\n"

    def sentences(self) -> list[str]:
        """One sentence per candidate: the acquisition that separates it best, or that it is
        told apart already, or that none of the library would."""
        return [(lambda words: words[:1].upper() + words[1:])(_sentence(record)) for record in self.effects]


def _sentence(record: dict) -> str:
    title, now, needed = record["title"], record["now_sigma"], record["detectable_sigma"]
    rival = f"{record['rival_title']} and the fitted parameters" if record["rival"] else "the fitted parameters"
    if record.get("skipped"):
        return f"{title}: not designed for ({record['skipped']})."
    if now >= needed:
        return (f"{title} is told apart from {rival} with the measured states already: separation {now:.1f} sigma "
                f"({needed:.1f} needed).")
    if not record["acquisitions"]:
        return f"{title}: no acquisition could be simulated."
    best = record["acquisitions"][0]
    how, linear = _checked_words(best)
    if best["separation_sigma"] < needed:
        return (f"No acquisition simulated tells {title} from {rival}: the best, {best['description']}, gives "
                f"{best['separation_sigma']:.1f} sigma{how} ({linear}now {now:.1f}; {needed:.1f} needed).")
    return (f"To tell {title} from {rival}, {best['description']}: expected separation "
            f"{best['separation_sigma']:.1f} sigma{how} ({linear}now {now:.1f}; {needed:.1f} needed).")


def _moved_words(moved: dict) -> str:
    """The refit's parameter changes ({key: change in its nuisance coordinate}) in words."""
    return ", ".join(f"{key} {change:+.3g}" for key, change in moved.items()) or "no parameter moved"


def _checked_words(acquisition: dict) -> tuple[str, str]:
    """How an acquisition's separation was checked (:func:`_check_best`), for its sentence: the
    words after the separation and those that open its brackets ("" where it was not checked)."""
    if "linear_sigma" not in acquisition:
        return "", ""
    refitted = acquisition["refitted"]
    if "failed" in refitted:
        return " by the linearisation", f"its check by refitting failed: {refitted['failed']}; "
    return (" once the fitted parameters are refitted to what it would show",
            f"{acquisition['linear_sigma']:.1f} by the linearisation at the fit; ")


def _check_best(record: dict, state: ModelState, measured: Observations, now: Sensitivities, kept: dict,
                stacks: dict, say: Callable[[str], None], count: int = CHECKED) -> None:
    """``record``'s ranked acquisitions with the best checked by refitting the fitted parameters to
    the data its effect would make (:func:`~BreastBiomechLib.discrepancy.design_check.refitted_separation`):
    its ``separation_sigma`` becomes the checked one (the linear one kept as ``linear_sigma``, the
    refit as ``refitted``), the ranking is made again, and the new best is checked too, up to
    ``count`` acquisitions. An acquisition whose refit cannot be made keeps its linear separation,
    with the reason (``refitted``: {"failed": why})."""
    from BreastBiomechLib.discrepancy.design_check import refitted_separation

    name, rival = record["effect"], record["rival"]
    for _ in range(count):
        best = next((a for a in record["acquisitions"] if "linear_sigma" not in a), None)
        if best is None or best is not record["acquisitions"][0]:
            return
        placed, simulated, there = kept[best["name"]]
        stacked = stacks[best["name"]]
        say(f"checking {best['name']} for {record['title']}: the fitted parameters refitted to what it would show")
        try:
            made = refitted_separation(state, placed, measured, simulated, now, there, stacked.fitted_span(), name,
                                       None if rival is None else stacked.effects[rival])
        except (RuntimeError, ValueError) as error:
            best.update(linear_sigma=best["separation_sigma"], refitted={"failed": str(error)})
            return
        best.update(linear_sigma=best["separation_sigma"], separation_sigma=made["sigma"], refitted=made)
        record["acquisitions"].sort(key=lambda a: -a["separation_sigma"])


def undecided(diagnosis: dict, effects: dict) -> list[str]:
    """The candidates a diagnosis round (its record's ``diagnosis``) could not tell apart, which
    the next measurement is designed for: those whose signature the fitted parameters reproduce
    (at least :data:`~BreastBiomechLib.discrepancy.diagnosis.ABSORBED` of it), those whose smallest
    detectable size lies beyond their range (``effects``: name -> :class:`Effect`), and, where the
    verdict is ambiguous, the effects it could not choose between."""
    from BreastBiomechLib.discrepancy.diagnosis import not_identifiable

    names = [c["name"] for c in diagnosis["candidates"]
             if not c.get("skipped") and not_identifiable(c, effects.get(c["name"]))]
    if diagnosis["verdict"] == "ambiguous":
        names += [n for n in (diagnosis.get("effect"), *(diagnosis.get("alternatives") or [])) if n]
    return [n for n in dict.fromkeys(names) if n in effects]


def with_rivals(diagnosis: dict, names: list[str]) -> list[str]:
    """``names`` and the closest rival of each among the round's tested candidates (by the
    correlation of their signatures beyond the fitted parameters), for :func:`design`."""
    from BreastBiomechLib.discrepancy.diagnosis import closest_rivals

    rivals = closest_rivals(diagnosis["candidates"], diagnosis.get("correlations") or {})
    return list(dict.fromkeys([*names, *[rivals[n][0] for n in names if n in rivals]]))


def acquisition_effects(now: Rows, names: list[str], designed_for=None) -> tuple[list[str], dict, list[str]]:
    """(the effects among ``names`` designed for: ``designed_for``'s, default all; the closest
    rival of each in the measured states' rows ``now``, for those it tested; the effects each
    simulated acquisition solves: those designed for and their rivals, in ``names``' order)."""
    chosen = list(names) if designed_for is None else [n for n in names if n in set(designed_for)]
    rivals = {name: now.closest_rival(name) for name in chosen if name in now.effects}
    solved = [n for n in names if n in chosen or n in rivals.values()]
    return chosen, rivals, solved


class _MadeFromTheSolve:
    """Observations made from the current model's solve (:func:`sensitivities` calls it with the
    displacement (N, 3) mm), kept as ``made`` for the rows."""

    def __init__(self, make: Callable[[np.ndarray], Observations]):
        self.make, self.made = make, None

    def __call__(self, displacement_mm: np.ndarray) -> Observations:
        self.made = self.make(displacement_mm)
        return self.made


def _with_measured_floor(simulated: ModelState, features: Observations, displacement_mm: np.ndarray,
                         lower_bound_mm: float) -> Observations:
    """A simulated acquisition's ``features`` with the model-error floor measured there as the
    diagnosis measures it (:func:`~BreastBiomechLib.discrepancy.floor.measure_floor`: the model
    ``simulated``, with the acquisition's plates and its simulated measurement, solved on the
    refined mesh; its solution on the fitting mesh ``displacement_mm``). Raises RuntimeError
    where the refined model does not solve."""
    from BreastBiomechLib.discrepancy.floor import measure_floor
    from BreastBiomechLib.discrepancy.regions import feature_regions

    regions = feature_regions(simulated.fitted, features, displacement_mm)
    return features.with_floor(measure_floor(simulated, features, displacement_mm, regions, lower_bound_mm).floor)


def _halved(fitted: FittedCase, state: ModelState, acquisition: Acquisition, queue) -> list[Acquisition]:
    """The one-plate ``acquisition``'s push half as far
    (:func:`~BreastBiomechLib.discrepancy.acquisitions.half_push`), to be simulated where the
    whole push does not solve at this fit (the model, or a variant the design needs); none for
    another kind, a push halved already or one in the ``queue``."""
    half = half_push(fitted, state, acquisition)
    return [half] if half is not None and half.name not in {a.name for a in queue} else []


def design(fitted: FittedCase, effects=None, kinds=KINDS, acquisitions: list[Acquisition] | None = None,
           noise: NoiseModel | None = None, alpha: float = 0.01, state: ModelState | None = None,
           progress: Callable[[str], None] | None = None, designed_for=None,
           observations: Observations | None = None, check: int = CHECKED) -> Design:
    """The :class:`Design` of the fitted case's next measurement for the candidate ``effects``
    (names; default the whole library, less those ``state`` has added) over ``acquisitions``
    (default :func:`acquisition_library`'s of ``kinds``: kinds or names), at the model ``state``
    (default the fit's; a diagnosis round's, with its added effects and refitted parameters) and
    the diagnosis level ``alpha``. The noise: ``observations``, the measured states' features as
    a diagnosis has them (default: made from the model's solution with the ``noise`` model's
    fixed floor); where they carry a floor measured from the case
    (:meth:`~BreastBiomechLib.discrepancy.observations.Observations.with_floor`), each simulated
    acquisition's floor is measured the same way (its model solved on the refined mesh,
    :func:`~BreastBiomechLib.discrepancy.floor.measure_floor`, ``noise.model_sd_mm`` its lower
    bound), so that the separations are predicted in the units a diagnosis of both scans
    realises them; else the ``noise`` model's fixed floor. ``designed_for`` (names among
    ``effects``; default all of them): the effects whose acquisitions are ranked; every candidate
    is a rival in the measured states, and each acquisition solves only these and their closest
    rivals there (a diagnosis designs for the few it could not tell apart: each acquisition's
    solves are as many fewer as the other candidates have parameters). A one-plate push whose
    model, or a variant of those, does not solve (an element inverted, also with a slower load)
    is simulated half as far too (``only-<plate>-half``); an acquisition whose model does not
    solve is in the design's ``failed``. Each designed effect's best ``check`` acquisitions are
    checked beyond the linearisation (:func:`_check_best`; 0: none)."""
    from dataclasses import replace

    say = progress or (lambda message: None)
    noise = replace(noise or NoiseModel(), floor="fixed")
    state = state or ModelState(fitted, fitted.z)
    candidates = [e for e in library(fitted, effects) if e.name not in state.added]
    names = [e.name for e in candidates]
    acquisitions = acquisition_library(fitted, state, kinds) if acquisitions is None else acquisitions
    measured_floor = observations is not None and observations.floor is not None
    rms_floor = float(np.sqrt(np.mean(observations.floor ** 2))) if measured_floor else None
    if observations is None:
        base = recorded_solution(fitted) if not state.added and np.array_equal(state.z, fitted.z) else None
        observations = observations_of(fitted, base, noise) if base is not None else _MadeFromTheSolve(
            lambda u: observations_of(fitted, u, noise))  # a diagnosis round's model: solved with its variants
    say("sensitivities in the measured states")
    measured_sens = sensitivities(state, observations, candidates, progress=say)
    measured = observations if isinstance(observations, Observations) else observations.made
    now = Rows.of(measured_sens, measured)
    chosen, rivals, solved = acquisition_effects(now, names, designed_for)
    stacks, failed, made, kept = {}, {}, [], {}
    undeformed = read_image(CaseLayout(fitted.case_dir).mr)
    queue = list(acquisitions)
    for acquisition in queue:  # a one-plate push that does not solve here adds its half to the queue
        say(f"simulating acquisition {acquisition.name}: {acquisition.description}")
        started = time.perf_counter()
        placed, simulated = placed_case(fitted, acquisition, undeformed, state.z), {}
        placed_state = ModelState(placed, state.z, state.added)

        def observed(u, acquisition=acquisition, simulated=simulated):
            simulated["case"] = simulated_measurement(fitted, acquisition, undeformed, state.z, u)
            return observations_of(simulated["case"], u, noise)

        seen = _MadeFromTheSolve(observed)
        try:  # the model there solved in one launch with its variants; its prediction taken as measured
            sens = sensitivities(placed_state, seen, library(placed, solved),
                                 progress=say)
        except RuntimeError as error:
            failed[acquisition.name] = f"in acquisition {acquisition.name}: {error}"
            queue += _halved(fitted, state, acquisition, queue)
            continue
        features, floor_note = seen.made, "measured" if measured_floor else "fixed"
        solved_s = time.perf_counter() - started
        if measured_floor:
            say(f"measuring the model-error floor in acquisition {acquisition.name}")
            try:
                features = _with_measured_floor(ModelState(simulated["case"], state.z, state.added), features,
                                                sens.displacement, noise.model_sd_mm)
            except RuntimeError as error:  # the measured states' RMS floor stands in for it
                features = features.with_floor(np.full(len(features), rms_floor))
                floor_note = f"the measured states' RMS floor ({rms_floor:.2f} mm): {error}"
        rows = Rows.of(sens, features)
        stacks[acquisition.name] = now.stacked(rows)
        kept[acquisition.name] = (placed_state, features, sens)
        made.append({"name": acquisition.name, "description": acquisition.description,
                     "planes": [dict(p) for p in acquisition.planes], "features": rows.n, "skipped": rows.skipped,
                     "floor": floor_note, "solves": sens.solves,
                     "seconds": {"sensitivities": round(solved_s, 1),
                                 "total": round(time.perf_counter() - started, 1)}})
        if any(why.startswith(UNSOLVED) for name, why in rows.skipped.items() if name in solved):
            queue += _halved(fitted, state, acquisition, queue)
    titles = {e.name: e.title for e in candidates}
    records = []
    for effect in candidates:
        name = effect.name
        if name not in chosen:
            continue
        record = {"effect": name, "title": titles[name],
                  "size": {p.name: p.step for p in effect.parameters},
                  "detectable_sigma": math.sqrt(detectable_noncentrality(1, alpha, POWER))}
        if name not in now.effects:
            records.append({**record, "skipped": now.skipped.get(name, "not tested"), "rival": None, "now_sigma": 0.0,
                            "acquisitions": []})
            continue
        rival = rivals[name]
        record.update(rival=rival, rival_title=titles.get(rival), now_sigma=now.separation(name, rival))
        ranked = [{"name": a["name"], "description": a["description"],
                   "separation_sigma": stacks[a["name"]].separation(name, rival)}
                  for a in made if name in stacks[a["name"]].effects and (rival is None or rival in stacks[a["name"]].effects)]
        record["acquisitions"] = sorted(ranked, key=lambda a: -a["separation_sigma"])
        if check:
            _check_best(record, state, measured, measured_sens, kept, stacks, say)
        records.append(record)
    return Design(records, made, failed, alpha, {"landmark_sd_mm": noise.landmark_sd_mm,
                                                 "model_sd_mm": noise.model_sd_mm, "channels": list(noise.channels),
                                                 "floor": "measured" if measured_floor else "fixed"},
                  state.to_dict())
