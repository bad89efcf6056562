"""One round of the diagnosis: is there a significant discrepancy between the current model and
the measured case, which candidate effect explains it, and is the answer clear.

1. Sensitivities of every feature to the fitted parameters and to each candidate's
   (:mod:`~BreastBiomechLib.discrepancy.sensitivity`, one batch of solves).
2. The overall test of the residual, pooled and per channel, and each candidate's score test
   likewise (:mod:`~BreastBiomechLib.discrepancy.statistics`); p-values Bonferroni-corrected
   over the channels and over the candidates tested. Candidates are ranked by the linearised
   dBIC of their score test (-S + dof ln n), so that a candidate with more parameters does not
   win by its degrees of freedom alone.
3. The significant candidates (at most ``refit_top``, by that rank) refitted
   (:mod:`~BreastBiomechLib.discrepancy.refit`) against the refit of the fitted parameters alone
   (the nested null model), with the LR test, dBIC, the localisation check (the residual's
   excess over the noise must sit in the regions where the candidate's signature sits) and the
   size of the change the refit makes to the features (``effect_mm``).
4. The verdict and its sentence (:mod:`~BreastBiomechLib.discrepancy.verdicts`, the rules and
   the words); the effect a missing-effect verdict names is refined by Gauss-Newton iterations.
   Whatever the verdict, a fitted parameter at an end of its range is reported: the data ask
   for more than the range allows, and a missing effect can hide in it (a chest wall that holds
   the breast fits as a stiffer pectoral muscle). Where the residual pushes such a parameter
   further out, it is held at its bound in the tests (it cannot move to absorb an effect).
   Where nothing significant is found, the candidates whose signature the fitted parameters
   reproduce (at least :data:`ABSORBED` of it) are said to be what this case could not have
   shown, with the fitted parameter that takes them up most.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from BreastBiomechLib.discrepancy import priors, statistics, verdicts
from BreastBiomechLib.discrepancy.design import Rows
from BreastBiomechLib.discrepancy.effects import Effect
from BreastBiomechLib.discrepancy.observations import Observations
from BreastBiomechLib.discrepancy.profile import profile_intervals
from BreastBiomechLib.discrepancy.refit import Refit, refine, refit
from BreastBiomechLib.discrepancy.regions import feature_regions as feature_regions_of
from BreastBiomechLib.discrepancy.sensitivity import Sensitivities, sensitivities
from BreastBiomechLib.discrepancy.state import ModelState
from BreastBiomechLib.discrepancy.variants import solve_variants
from BreastBiomechLib.timing import staged

VERDICTS = verdicts.VERDICTS
EDGE = 0.005  # a fitted parameter this close to an end of its range (unit coordinates) is at it
ABSORBED = 0.8  # a candidate this much of whose signature the fitted parameters reproduce is hard to see
TAKEN_UP = 0.5  # a candidate too small to see is said taken up by the parameter reproducing this much of it
# two candidates whose signatures correlate this much once the fitted parameters are accounted for
# cannot be told apart by this case: the part of one the other cannot reproduce is sqrt(1 - 0.8^2),
# 0.6 of it
INSEPARABLE = 0.8


@dataclass
class DiagnosisSettings:
    """Decision thresholds: ``alpha`` the family-wise significance level, ``refit_top`` how many
    significant candidates are refitted, ``min_explained`` the share of the residual (sum of
    squares, each feature by its measurement's precision with the fixed floor:
    :func:`removed_share`) a named effect's refit must remove beyond the same refit of the fitted
    parameters alone, ``bic_threshold`` the largest dBIC against that nested refit that confirms
    (-10: very strong evidence, Kass and Raftery), ``ambiguity_correlation`` and ``ambiguity_bic`` when two
    confirmed candidates cannot be told apart, ``min_localisation`` the overlap of residual and
    signature over the regions a candidate needs; ``refine_iterations`` the Gauss-Newton
    iterations of the refit of the effect that is added, ``profile`` whether its parameters'
    95 % intervals are profile-likelihood ones (:mod:`~BreastBiomechLib.discrepancy.profile`:
    a few solves more, right where an effect saturates) rather than linearised only."""

    alpha: float = 0.01
    refit_top: int = 3
    min_explained: float = 0.4
    bic_threshold: float = -10.0
    ambiguity_correlation: float = 0.9
    ambiguity_bic: float = 6.0
    min_localisation: float = 0.5
    min_effect: float = 1.0
    refine_iterations: int = 2
    profile: bool = True


@dataclass
class Candidate:
    """One candidate's evidence: its score test (``statistic``, ``dof``, ``p_value`` pooled over
    the features, each channel's own in ``channels``, and ``p_adjusted``: the smallest of the
    family Bonferroni-corrected over it and over the candidates), ``linear_delta_bic`` (-S + dof
    ln n, its rank), the share of the residual its signature could explain
    (``explained_fraction``), the linearised ``estimate`` and its ``sd``, where its signature
    sits (``signature_regions``: share per region), the ``localisation`` overlap, and after a
    refit the LR test and dBIC against the refit of the fitted parameters alone (the nested null
    model, stepped the same way), the share of that refit's residual it removed and the values it
    refitted to; ``absorbed`` the share of its signature the fitted parameters reproduce
    (:func:`~BreastBiomechLib.discrepancy.statistics.absorbed_share`) and ``absorbed_by`` the
    fitted parameter that alone reproduces most of it ({"name", "correlation"}); ``detectable``
    the smallest size of each of its parameters (its units, away from the off value; None: none)
    the verdict would name at this case's noise and model floor with 80 % power (:func:`_detectable`,
    along its secant);
    ``separations`` its signature at its realistic size beyond the fitted parameters ("": alone)
    and beyond them and each other tested candidate (by name), in sigma of this round's noise:
    what :mod:`~BreastBiomechLib.discrepancy.design` predicts for a further scan, realised;
    ``parameters`` the names of its parameters, in the order of its estimate; or the reason it
    was ``skipped``."""

    name: str
    title: str
    acts_in: str
    statistic: float = float("nan")
    dof: int = 0
    p_value: float = float("nan")
    p_adjusted: float = float("nan")
    explained_fraction: float = float("nan")
    estimate: list = field(default_factory=list)
    sd: list = field(default_factory=list)
    signature_regions: dict = field(default_factory=dict)
    localisation: float = float("nan")
    refit: dict | None = None
    absorbed: float = float("nan")
    absorbed_by: dict = field(default_factory=dict)
    channels: dict = field(default_factory=dict)
    linear_delta_bic: float = float("nan")
    detectable: list = field(default_factory=list)
    separations: dict = field(default_factory=dict)
    parameters: list = field(default_factory=list)
    skipped: str = ""

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class Diagnosis:
    """A round's result: the ``verdict`` (one of :data:`VERDICTS`), the ``effect`` named (or the
    alternatives of an ambiguous verdict), a ``sentence`` saying it with the evidence, the
    ``overall`` test, the ``candidates`` ranked by p-value, the residual by ``regions``, their
    ``correlations``, the chosen :class:`~BreastBiomechLib.discrepancy.refit.Refit` (``refitted``)
    and the ``sensitivities`` (with the solution of the current model); ``held`` the nuisance
    parameters held at a bound of their range in the tests (the residual pushes them out of
    it), ``edges`` the fit's parameters at an end of their range and ``conflicts`` its moduli
    beyond their published range, each with the tests held inside it
    (:mod:`~BreastBiomechLib.discrepancy.priors`)."""

    verdict: str
    effect: str | None
    alternatives: list[str]
    sentence: str
    overall: dict
    candidates: list[Candidate]
    regions: dict
    correlations: dict
    refitted: Refit | None
    sensitivities: Sensitivities
    feature_regions: np.ndarray
    refits: dict = field(default_factory=dict)
    held: list = field(default_factory=list)
    edges: list = field(default_factory=list)
    conflicts: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"verdict": self.verdict, "effect": self.effect, "alternatives": self.alternatives,
                "sentence": self.sentence, "overall": self.overall, "held": self.held, "edges": self.edges,
                "prior_conflicts": self.conflicts,
                "candidates": [c.to_dict() for c in self.candidates], "regions": self.regions,
                "correlations": self.correlations, "solves": self.sensitivities.solves,
                "skipped": self.sensitivities.skipped}


def range_end(value: float, lower: float, upper: float) -> str:
    """"top" or "bottom" where ``value`` lies within :data:`EDGE` (a share of the range) of that
    end of [``lower``, ``upper``], else "" (also for an empty range, which has no ends to press on)."""
    if not upper > lower:
        return ""
    share = (value - lower) / (upper - lower)
    return "top" if share >= 1.0 - EDGE else "bottom" if share <= EDGE else ""


def parameters_at_edges(state: ModelState, held: list[str] = ()) -> list[dict]:
    """The fit's free parameters of ``state`` within :data:`EDGE` of an end of their range (unit
    coordinates): {"name", "value" (the parameter's unit: Pa for moduli), "end": "top"|"bottom",
    "held": whether the residual pushes it further out (``held``: those keys), so that the
    tests held it there}."""
    space = state.fitted.space
    values = space.values(state.z)
    ends = {key: range_end(z, 0.0, 1.0) for key, z in zip(space.keys, state.z)}
    return [{"name": key, "value": values[key], "end": end, "held": key in held} for key, end in ends.items() if end]


def ends_of_range(state: ModelState) -> tuple[np.ndarray, np.ndarray]:
    """Which nuisance parameters of ``state`` (the order of :meth:`ModelState.nuisance`) are within
    :data:`EDGE` of the top and of the bottom of their range (as a share of the range)."""
    ends = np.array([range_end(value, lower, upper) for _, value, lower, upper in state.nuisance()], dtype=object)
    return ends == "top", ends == "bottom"


def edges_sentence(edges: list[dict]) -> str:
    """What :func:`parameters_at_edges` found, as a sentence ("" when nothing)."""
    if not edges:
        return ""
    listed = ", ".join(f"{e['name']} ({e['value']:.4g}) at the {e['end']}" for e in edges)
    held = [e["name"] for e in edges if e.get("held")]
    pushed = (f" The residual pushes {', '.join(held)} further out: the tests held {'it' if len(held) == 1 else 'them'} "
              "there." if held else "")
    return (f"Fitted at an end of its range: {listed}; the data ask for more than the range allows, and a "
            "missing effect can hide in such a parameter (a chest wall that holds the breast fits as a stiffer "
            f"pectoral muscle) - check the range before trusting the verdict.{pushed}")


def _detectable(sensitivity: np.ndarray, q_theta: np.ndarray, alpha: float, observations: Observations,
                settings: DiagnosisSettings) -> list:
    """The smallest size of each of a candidate's parameters (whitened ``sensitivity`` (n, k) per
    unit) the verdict would name, as a record's list (None where none would be): its score test
    at level ``alpha`` and its likelihood ratio past the BIC threshold
    (:func:`~BreastBiomechLib.discrepancy.statistics.minimum_detectable`, 80 % power), and its
    change of the features beyond what the fitted parameters take up (``q_theta``) at least
    ``min_effect`` x the model floor where it acts (:func:`~BreastBiomechLib.discrepancy.verdicts.floor_ratio`):
    the larger of the two, so that an effect hidden at that size is named, not only seen."""
    b = np.atleast_2d(sensitivity.T).T
    n, k = b.shape
    sizes = statistics.minimum_detectable(b, q_theta, alpha, power=0.8,
                                          least_statistic=-settings.bic_threshold + k * np.log(max(n, 1)))
    beyond = statistics.project_off(b, q_theta) * observations.sigma[:, None]  # mm per unit of each parameter
    for j in range(k):
        ratio = verdicts.floor_ratio(beyond[:, j], observations.feature_floor, settings.min_effect)
        sizes[j] = max(sizes[j], 1.0 / ratio if ratio > 0 else np.inf)
    return [float(v) if np.isfinite(v) else None for v in sizes]


def not_identifiable(candidate: dict, effect: Effect | None) -> bool:
    """Whether a round said of ``candidate`` (its record, :meth:`Candidate.to_dict`) that this
    case could not have shown it: at least :data:`ABSORBED` of its signature reproduced by the
    fitted parameters, or (given its ``effect``) every parameter's smallest detectable size past
    both ends of its range, or none (an effect seen along one of its parameters could be shown)."""
    absorbed = candidate.get("absorbed")
    if absorbed is not None and absorbed == absorbed and absorbed >= ABSORBED:
        return True
    sizes = list(zip(effect.parameters, candidate.get("detectable") or [])) if effect is not None else []
    return bool(sizes) and all(size is None or size > max(p.upper - p.off, p.off - p.lower) for p, size in sizes)


def beyond_range(candidate: Candidate, effects: dict) -> list[str]:
    """The parameters of ``candidate`` whose smallest detectable size reaches past both ends of
    their range from the off value ("mu 2.1, its range 0-1.5"): no value the effect may take
    could have been seen here. ``effects`` maps names to :class:`Effect`."""
    effect = effects.get(candidate.name)
    if effect is None or not candidate.detectable:
        return []
    out = []
    for parameter, size in zip(effect.parameters, candidate.detectable):
        reach = max(parameter.upper - parameter.off, parameter.off - parameter.lower)
        if size is None or size > reach:
            shown = "none" if size is None else f"{size:.3g} {parameter.unit}".strip()
            out.append(f"{parameter.name} {shown}, its range {parameter.lower:g} to {parameter.upper:g}")
    return out


def absorbed_sentence(candidates: list[Candidate], effects: dict | None = None, missing: bool = False) -> str:
    """The tested candidates this case could not have shown ("" when none): those whose signature
    the fitted parameters reproduce (at least :data:`ABSORBED` of it), and those (with
    ``effects``, name -> :class:`Effect`) whose smallest detectable size lies beyond their range,
    each with the fitted parameter that would take it up where the fitted parameters reproduce
    at least :data:`TAKEN_UP` of its signature. ``missing``: said after an unexplained
    discrepancy, where such an effect may be what is missing (and a further measured state is
    what would tell)."""
    tested = [c for c in candidates if not c.skipped]
    hidden = [c for c in tested if c.absorbed >= ABSORBED]
    parts = []
    if hidden:
        listed = "; ".join(f"{c.title} ({c.absorbed:.0%} of its signature, chiefly by {c.absorbed_by['name']}, "
                           f"correlation {c.absorbed_by['correlation']:.2f})" for c in hidden)
        consequence = ("such an effect may be what is missing here, fitted in part as those parameters; a further "
                       "measured state would tell (`diagnose --design`)" if missing else
                       "such an effect, if present, has been fitted as those parameters")
        parts.append(f"What this case could not have shown, since the fitted parameters reproduce what it would "
                     f"change: {listed}; {consequence}.")
    small = [(c, beyond_range(c, effects or {})) for c in tested if c not in hidden]
    small = [(c, ends) for c, ends in small if ends]
    if small:
        listed = "; ".join(f"{c.title} (smallest size its test would see: {'; '.join(ends)}{_taken_up(c)})"
                           for c, ends in small)
        parts.append(f"Too small to see at this case's noise, whatever its size within its range: {listed}.")
    return " ".join(parts)


def _taken_up(candidate: Candidate) -> str:
    """"; X % of it would be taken up as P" where the fitted parameters reproduce at least
    :data:`TAKEN_UP` of ``candidate``'s signature, P the one that chiefly does ("" otherwise)."""
    name = (candidate.absorbed_by or {}).get("name")
    if not name or not candidate.absorbed >= TAKEN_UP:
        return ""
    return f"; {candidate.absorbed:.0%} of it would be taken up as {name}"


def closest_rivals(candidates: list[dict], correlations: dict) -> dict[str, tuple[str, float]]:
    """For each tested candidate (records of :meth:`Candidate.to_dict`) the other tested one whose
    signature correlates most with its own once the fitted parameters are accounted for
    (``correlations``, "a|b" -> the largest canonical correlation), and that correlation."""
    tested = [c["name"] for c in candidates if not c.get("skipped")]
    out = {}
    for name in tested:
        pairs = [(correlations.get(f"{name}|{other}", correlations.get(f"{other}|{name}")), other)
                 for other in tested if other != name]
        pairs = [(value, other) for value, other in pairs if value is not None]
        if pairs:
            value, other = max(pairs)
            out[name] = (other, float(value))
    return out


def inseparable_sentence(candidates: list[dict], correlations: dict, threshold: float = INSEPARABLE) -> str:
    """What this case cannot tell apart: the pairs of tested candidates whose signatures correlate
    at ``threshold`` or more once the fitted parameters are accounted for, strongest first, or that
    there are none."""
    titles = {c["name"]: c.get("title", c["name"]) for c in candidates if not c.get("skipped")}
    pairs = sorted(((value, *key.split("|")) for key, value in correlations.items()
                    if value >= threshold and all(name in titles for name in key.split("|"))), reverse=True)
    if not pairs:
        return (f"No two tested candidates' signatures correlate at {threshold:.2f} or more once the fitted "
                "parameters are accounted for: the case tells each from the others.")
    listed = "; ".join(f"{titles[a]} and {titles[b]} ({value:.2f})" for value, a, b in pairs)
    return (f"This case cannot tell apart (their signatures correlate at {threshold:.2f} or more once the fitted "
            f"parameters are accounted for): {listed}; either of a pair may stand for the other, and a second "
            "measured state is what would separate them.")


def _shares(values: np.ndarray, regions: np.ndarray) -> dict[str, float]:
    """The share of the positive ``values`` in each region."""
    positive = np.maximum(values, 0.0)
    total = positive.sum()
    names = sorted(set(regions.tolist()))
    if total <= 0:
        return {name: 0.0 for name in names}
    return {name: float(positive[regions == name].sum() / total) for name in names}


def _absorbed_by(sensitivity: np.ndarray, nuisance: np.ndarray, held: np.ndarray, keys: list[str]) -> dict:
    """The fitted parameter (of the whitened ``nuisance`` columns not ``held``) whose change
    alone correlates most with the whitened candidate ``sensitivity``: {"name", "correlation"}
    ({} when there is none)."""
    empty = np.zeros((len(sensitivity), 0))
    scores = [(statistics.canonical_correlation(sensitivity, nuisance[:, [k]], empty), key)
              for k, key in enumerate(keys) if not held[k]]
    if not scores:
        return {}
    correlation, key = max(scores)
    return {"name": key, "correlation": correlation}


def region_summary(observations: Observations, residual: np.ndarray, regions: np.ndarray) -> dict:
    """Per region and channel: the features' count, RMS residual (mm) and mean squared whitened
    residual (about 1 where the residual is noise)."""
    out = {}
    whitened = residual / observations.sigma
    for name in sorted(set(regions.tolist())):
        for channel in sorted(set(observations.channel.tolist())):
            mask = (regions == name) & (observations.channel == channel)
            if mask.any():
                out.setdefault(name, {})[channel] = {
                    "features": int(mask.sum()), "rms_mm": float(np.sqrt(np.mean(residual[mask] ** 2))),
                    "mean_square_whitened": float(np.mean(whitened[mask] ** 2))}
    return out


def adopt(state: ModelState, observations: Observations, sens: Sensitivities, candidate: Candidate, effect: Effect,
          refits: dict[str, Refit], iterations: int, progress: Callable[[str], None] | None = None,
          profile: bool = True, tolerance: float = 1.0) -> Refit:
    """The refit of ``state`` with ``candidate``'s ``effect`` added, refined by ``iterations``
    Gauss-Newton iterations of every fitted parameter (warm start: its confirmation refit in
    ``refits``, else one made now from the round's sensitivities ``sens``), with its parameters'
    profile intervals where ``profile`` (kept from an earlier call when nothing was refined),
    which hold the values whose features lie within ``tolerance`` times the model-error floor of
    the estimate's (:mod:`~BreastBiomechLib.discrepancy.profile`). Records the refined values and
    the intervals (with the data's alone, ``data_interval``) in ``candidate.refit``; 0 iterations
    keep the confirmation refit as it is."""
    say = progress or (lambda message: None)
    chosen = refits.get(candidate.name)
    if chosen is None:
        say(f"refitting with {candidate.name}")
        made = refit(state, observations, sens, [effect])
        if not made or not made[0].ok:
            raise RuntimeError(f"{candidate.title}: no refit with it solves ({made[0].status if made else 'not built'}); "
                               "it cannot be added to this model")
        chosen = refits[candidate.name] = made[0]
    design = None  # the features' change per unit of each of the refit's parameters, for its profile
    if iterations > 0:
        say(f"refining the refit with {candidate.name}")
        refined = refine(chosen.state, observations, iterations, say, current=chosen.outcome)
        weights = 1.0 / observations.sigma
        after = observations.residual(refined.outcome.displacement)
        values = refined.state.added[candidate.name][1]
        keys = [f"{candidate.name}:{i}" for i in range(len(values))]
        sd = refined.sd
        chosen = replace(chosen, values=values, state=refined.state, displacement=refined.outcome.displacement,
                         residual_after=after, rss_after=float(np.sum((weights * after) ** 2)), profile=None,
                         sd=np.array([sd[k] for k in keys]) if all(k in sd for k in keys) else chosen.sd)
        if refined.sensitivities is not None:
            design = refined.sensitivities.nuisance
    if profile and chosen.profile is None:
        if design is None and candidate.name in sens.effects:  # not refined: the round's sensitivities
            design = np.hstack([sens.nuisance, sens.effects[candidate.name]])
        if design is not None:
            profiled, better = profile_intervals(chosen.state, observations, candidate.name, design, chosen.rss_after,
                                                 say, residual_at_estimate=chosen.residual_after, tolerance=tolerance)
            chosen = replace(chosen, profile=[p.to_dict() for p in profiled])
            if better is not None:
                chosen = _moved_to_the_least(chosen, better, candidate.name, observations, say)
    candidate.refit = candidate.refit or {"status": chosen.status, "values": chosen.values.tolist(),
                                          "sd": chosen.sd.tolist(), "described": chosen.effect.describe(chosen.values),
                                          "rss_before": chosen.rss_before, "rss_after": chosen.rss_after}
    candidate.refit.update({"refined_values": chosen.values.tolist(), "refined_sd": chosen.sd.tolist(),
                            "interval": interval(chosen),
                            "interval_kind": "profile" if chosen.profile else "linearised",
                            "interval_open": [p["open"] for p in chosen.profile] if chosen.profile else [],
                            "data_interval": [p["data_interval"] for p in chosen.profile] if chosen.profile else [],
                            "profile": chosen.profile or [],
                            "refined_described": chosen.effect.describe(chosen.values),
                            "rss_refined": chosen.rss_after,
                            "refine_iterations": candidate.refit.get("refine_iterations", 0) + iterations})
    return chosen


def _moved_to_the_least(chosen: Refit, better: np.ndarray, name: str, observations: Observations,
                        say: Callable[[str], None]) -> Refit:
    """``chosen`` (the refined refit of effect ``name``, with its profile) moved to the value its
    profile walked past that fitted the features better (``better``: every nuisance parameter
    there, the others at their linearised re-fit), where a solve confirms that it does: the
    Gauss-Newton refinement stopped short of the least, and the profile found it. Its intervals
    stand (their deviances are counted from the least value walked); the profile records the
    estimate it moved from (``moved_from``)."""
    say(f"solving the {name} refit at the better value its profile found")
    trial = chosen.state.with_nuisance(better)
    fitted = trial.fitted
    outcome = solve_variants([trial.variant()], fitted.mesh.nodes, fitted.relaxation, fitted.device)[0]
    if not outcome.ok:
        return chosen
    after = observations.residual(outcome.displacement)
    rss = float(np.sum((after / observations.sigma) ** 2))
    if not rss < chosen.rss_after:
        return chosen
    values = trial.added[name][1]
    profile = [{**p, "moved_from": p["estimate"], "estimate": float(v)} for p, v in zip(chosen.profile, values)]
    return replace(chosen, values=values, state=trial, displacement=outcome.displacement, residual_after=after,
                   rss_after=rss, profile=profile)


def diagnose(state: ModelState, observations: Observations, candidates: list[Effect],
             settings: DiagnosisSettings | None = None,
             progress: Callable[[str], None] | None = None, excluded: dict[str, str] | None = None) -> Diagnosis:
    """One round of the diagnosis of ``state`` against ``observations`` over ``candidates``
    (the library's effects; those already added, unavailable or ``excluded`` ({name: reason},
    e.g. rejected by the user) are reported as skipped). The fit's parameters at an end of their
    range are listed in ``edges``, its moduli beyond their published range in ``conflicts`` (each
    with the candidates tested again with it held inside), both said after the verdict's sentence."""
    result = _decide(state, observations, candidates, settings, progress, excluded)
    result.edges = parameters_at_edges(state, result.held)
    by_name = {effect.name: effect for effect in candidates}
    hidden = (absorbed_sentence(result.candidates, by_name, missing=result.verdict == verdicts.UNEXPLAINED)
              if result.verdict in (verdicts.NONE, verdicts.UNEXPLAINED) else "")
    if hidden:
        result.sentence = f"{result.sentence} {hidden}"
    if result.edges:
        result.sentence = f"{result.sentence} {edges_sentence(result.edges)}"
    if result.conflicts:
        titles = {effect.name: effect.title for effect in candidates}
        result.sentence = f"{result.sentence} {priors.conflict_sentence(result.conflicts, result.effect, titles)}"
    return result


@staged("statistics")
def _decide(state: ModelState, observations: Observations, candidates: list[Effect],
            settings: DiagnosisSettings | None, progress: Callable[[str], None] | None,
            excluded: dict[str, str] | None) -> Diagnosis:
    settings = settings or DiagnosisSettings()
    say = progress or (lambda message: None)
    fitted = state.fitted
    skipped = {}
    testable = []
    for effect in candidates:
        reason = ("already added" if effect.name in state.added else (excluded or {}).get(effect.name)
                  or effect.unavailable_at(fitted, state.added))
        if reason:
            skipped[effect.name] = reason
        else:
            testable.append(effect)
    # fitted moduli beyond their published range: each also solved held at its range's end
    keys = {key for key, *_ in state.nuisance()}
    conflicts = [c for c in priors.prior_conflicts(fitted.space, state.z) if c["name"] in keys]
    sens = sensitivities(state, observations, testable, say, held={c["name"]: c["z_bound"] for c in conflicts})
    sens.skipped = {**skipped, **sens.skipped}
    weights = 1.0 / observations.sigma
    residual = observations.measured - sens.features
    whitened = weights * residual
    nuisance = weights[:, None] * sens.nuisance
    held = statistics.pushed_out(nuisance, whitened, *ends_of_range(state))
    free = nuisance[:, ~held]
    q_theta = statistics.basis(free)
    overall = statistics.overall_by_channel(whitened, free, observations.channel)
    feature_regions = feature_regions_of(fitted, observations, sens.displacement)
    excess = whitened ** 2 - 1.0
    residual_shares = _shares(excess, feature_regions)
    tested = [e for e in testable if e.name in sens.effects]
    m = max(len(tested), 1)
    n = len(observations)
    ranked: list[Candidate] = []
    for effect in tested:
        b = weights[:, None] * sens.effects[effect.name]
        test = statistics.score_by_channel(whitened, free, b, observations.channel)
        change = (b @ np.atleast_1d(test["estimate"])) ** 2
        signature = _shares(change, feature_regions)
        overlap = float(sum(min(signature.get(k, 0.0), residual_shares.get(k, 0.0)) for k in residual_shares))
        ranked.append(Candidate(effect.name, effect.title, effect.acts_in, test["statistic"], test["dof"],
                                test["p_value"], min(1.0, test["p_combined"] * m), test["explained_fraction"],
                                np.atleast_1d(test["estimate"]).tolist(), np.atleast_1d(test["sd"]).tolist(),
                                signature, overlap, absorbed=statistics.absorbed_share(b, q_theta),
                                absorbed_by=_absorbed_by(b, nuisance, held, sens.nuisance_keys),
                                channels=test["channels"],
                                linear_delta_bic=-test["statistic"] + test["dof"] * np.log(n),
                                detectable=_detectable(b, q_theta, settings.alpha / (m * (1 + len(test["channels"]))),
                                                       observations, settings),
                                parameters=[p.name for p in effect.parameters]))
    rows = Rows.of(sens, observations)  # each signature at its realistic size, as the design's
    for c in ranked:
        c.separations = {rival or "": rows.separation(c.name, rival) for rival in [None, *rows.effects] if rival != c.name}
    ranked.sort(key=lambda c: (c.linear_delta_bic, c.p_adjusted))
    for name, reason in sens.skipped.items():
        effect = next((e for e in candidates if e.name == name), None)
        ranked.append(Candidate(name, effect.title if effect else name, effect.acts_in if effect else "",
                                skipped=reason))
    correlations = {}
    for i, a in enumerate(tested):
        for b in tested[i + 1:]:
            correlations[f"{a.name}|{b.name}"] = statistics.canonical_correlation(
                weights[:, None] * sens.effects[a.name], weights[:, None] * sens.effects[b.name], q_theta)
    # the tests again with each conflicting modulus held at its range's end: the residual of the
    # model solved there (linearised where that model did not solve)
    signatures = {e.name: weights[:, None] * sens.effects[e.name] for e in tested} if conflicts else {}
    for conflict in conflicts:
        there = sens.held.get(conflict["name"])
        solved = None if there is None else weights * (observations.measured - observations.predicted(there))
        conflict["retest"] = priors.held_in_range(whitened, nuisance, ~held, sens.nuisance_keys.index(conflict["name"]),
                                                  conflict["z_bound"] - state.z[conflict["index"]], signatures,
                                                  observations.channel, settings.alpha,
                                                  {c.name: c.p_adjusted for c in ranked}, solved)
    regions = region_summary(observations, residual, feature_regions)
    base = dict(overall=overall, candidates=ranked, regions=regions, correlations=correlations,
                sensitivities=sens, feature_regions=feature_regions, refits={},
                held=[key for key, h in zip(sens.nuisance_keys, held) if h], conflicts=conflicts)
    marks = observations.channel == "landmarks"
    evidence = verdicts.Evidence(overall, [], correlations, _rms(residual), _largest(regions),
                                 _rms(observations.feature_floor),
                                 landmark_noise=(_rms(observations.measurement_sd[marks]),
                                                 _rms(observations.feature_floor[marks]))
                                 if marks.any() and observations.measurement_sd is not None else None)
    evidence.candidates = [c.to_dict() for c in ranked]
    chosen = [c for c in ranked if not c.skipped and c.p_adjusted < settings.alpha][:settings.refit_top]
    if not chosen and not verdicts.overall_significant(evidence, settings.alpha):
        decision = verdicts.decide(evidence, settings)
        return Diagnosis(decision.verdict, None, [], decision.sentence, refitted=None, **base)
    by_name = {e.name: e for e in tested}
    say(f"refitting {', '.join(c.name for c in chosen) or 'no candidate'}")
    made = refit(state, observations, sens, [by_name[c.name] for c in chosen] + [None])
    refits = {r.effect.name: r for r in made if r.effect is not None}
    base["refits"] = refits
    # the nested null model refitted by the same step: what the fitted parameters alone remove
    fitted_only = next((r for r in made if r.effect is None and r.ok), None)
    rss_null = min(fitted_only.rss_after, fitted_only.rss_before) if fitted_only else None
    reference = (fitted_only.residual_after if fitted_only and fitted_only.rss_after <= fitted_only.rss_before
                 else residual)
    for candidate in chosen:
        r = refits.get(candidate.name)
        if r is None:
            candidate.refit = {"status": "the refit could not be built"}
            continue
        k = len(r.effect.parameters)
        null = r.rss_before if rss_null is None else rss_null
        lr = statistics.likelihood_ratio(null, r.rss_after, k, n)
        candidate.refit = {"status": r.status, "values": r.values.tolist(), "sd": r.sd.tolist(),
                           "described": r.effect.describe(r.values), "rss_before": r.rss_before,
                           "rss_fitted_only": null, "rss_after": r.rss_after, "rss_linear": r.rss_linear,
                           "lr": lr["statistic"], "lr_p_adjusted": min(1.0, lr["p_value"] * m),
                           "delta_bic": lr["delta_bic"],
                           "removed": removed_share(reference, r.residual_after, observations.base_sigma),
                           "removed_whitened": max(null - r.rss_after, 0.0) / null if null > 0 else 0.0,
                           "excess_explained": statistics.excess_explained(null, r.rss_after, overall["dof"],
                                                                           overall["dof"] - k),
                           "effect_mm": verdicts.effect_size_mm(reference - r.residual_after),
                           "floor_mm": _rms(observations.feature_floor[
                               verdicts.where_it_acts(reference - r.residual_after)]),
                           "at_range_ends": range_ends(r)}
        if r.note:
            candidate.refit["note"] = r.note
    evidence.candidates = [c.to_dict() for c in ranked]
    if fitted_only and fitted_only.rss_before > 0:
        evidence.fitted_alone_removed = 1.0 - rss_null / fitted_only.rss_before
    decision = verdicts.decide(evidence, settings)
    if decision.verdict != verdicts.MISSING:
        return Diagnosis(decision.verdict, None, decision.alternatives, decision.sentence, refitted=None, **base)
    best = next(c for c in ranked if c.name == decision.effect)
    chosen_refit = adopt(state, observations, sens, best, by_name[best.name], refits, settings.refine_iterations, say,
                         settings.profile, settings.min_effect)
    return Diagnosis(verdicts.MISSING, best.name, [],
                     verdicts.missing_effect_sentence(best.to_dict(), _bound_note(chosen_refit), evidence, settings),
                     refitted=chosen_refit, **base)


def removed_share(before: np.ndarray, after: np.ndarray, sigma: np.ndarray) -> float:
    """The share (0-1) of the residual ``before`` (n,) mm that a refit leaving ``after`` removed,
    each feature weighted by ``sigma`` (n,) mm: the measurement's precision with the fixed floor
    (:attr:`~BreastBiomechLib.discrepancy.observations.Observations.base_sigma`), not the
    measured floor, which is largest where the model's discretisation is coarsest - the plates'
    contact, where friction acts - and would discount an effect's share exactly where it acts.
    The tests of significance use the measured floor."""
    total = float(np.sum((np.asarray(before, float) / sigma) ** 2))
    if total <= 0:
        return 0.0
    return max(total - float(np.sum((np.asarray(after, float) / sigma) ** 2)), 0.0) / total


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.asarray(values, float) ** 2))) if np.size(values) else 0.0


def _largest(regions: dict) -> str:
    """The region and channel of :func:`region_summary` with the largest RMS residual, as
    "region (channel)" ("" when none)."""
    rows = [(figures["rms_mm"], f"{name} ({channel})") for name, channels in regions.items()
            for channel, figures in channels.items()]
    return max(rows)[1] if rows else ""


def interval(chosen: Refit, z: float = 1.96) -> list[list[float]]:
    """Each refitted parameter's 95 % interval: its profile interval where the refit has one,
    else ``z`` sd either side of its value (from the linearised information) clipped to the
    parameter's range; [[low, high], ...] in its units."""
    if chosen.profile:
        return [list(p["interval"]) for p in chosen.profile]
    return [[float(max(p.lower, v - z * s)), float(min(p.upper, v + z * s))]
            for p, v, s in zip(chosen.effect.parameters, chosen.values, chosen.sd)]


def range_ends(chosen: Refit) -> list[str]:
    """The refitted effect's parameters within :data:`EDGE` of an end of their range, as phrases
    ("mu at the top of its range (1.5)")."""
    ends = []
    for parameter, value in zip(chosen.effect.parameters, chosen.values):
        end = range_end(value, parameter.lower, parameter.upper)
        if end:
            unit = f" {parameter.unit}" if parameter.unit else ""
            ends.append(f"{parameter.name} at the {end} of its range ({value:.4g}{unit})")
    return ends


def _bound_note(chosen: Refit) -> str:
    """A sentence on the added effect's parameters that its refit left within :data:`EDGE` of
    an end of their range ("" when none): their value is a bound the data press against, not an
    estimate (friction beyond sticking, for one, changes nothing)."""
    ends = range_ends(chosen)
    if not ends:
        return ""
    return (f" Refitted to an end of its range: {', '.join(ends)}; the value is a bound the data press against, "
            "not an estimate (its range is where the effect stays physical, or beyond it nothing changes).")
