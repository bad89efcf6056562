"""One round of the diagnosis: is there a significant discrepancy between the current model and
the measured case, which candidate effect explains it, and is the answer clear.

1. Sensitivities of every feature to the fitted parameters and to each candidate's
   (:mod:`~BreastBiomechLib.discrepancy.sensitivity`, one batch of solves).
2. The overall test of the residual and each candidate's score test
   (:mod:`~BreastBiomechLib.discrepancy.statistics`); p-values Bonferroni-corrected over the
   candidates tested.
3. The significant candidates (at most ``refit_top``, by p-value) refitted
   (:mod:`~BreastBiomechLib.discrepancy.refit`) and confirmed by the likelihood-ratio test, BIC
   and a localisation check: the residual's excess over the noise must sit in the regions where
   the candidate's signature sits (overlap of the two distributions over the regions).
4. The verdict: **missing effect** (one confirmed candidate's refit removes at least
   ``min_explained`` of the residual's sum of squares; its parameters are then refined by
   Gauss-Newton iterations), **ambiguous** (another confirmed candidate is
   nearly as good by BIC and its signature correlates above ``ambiguity_correlation``),
   **unexplained discrepancy** (significant, but no candidate confirmed or explains enough: the
   answer when the missing effect is not in the library) or **no significant discrepancy**.
   Whatever the verdict, a fitted parameter at an end of its range is reported: the data ask
   for more than the range allows, and a missing effect can hide in it (a chest wall that holds
   the breast fits as a stiffer pectoral muscle). Where the residual pushes such a parameter
   further out, it is held at its bound in the tests (it cannot move to absorb an effect).
   Where no effect is named, the candidates whose signature the fitted parameters reproduce
   (at least :data:`ABSORBED` of it) are said to be hard to see at this fit, with the fitted
   parameter that takes them up most.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from BreastBiomechLib.discrepancy import statistics
from BreastBiomechLib.discrepancy.effects import Effect
from BreastBiomechLib.discrepancy.observations import Observations
from BreastBiomechLib.discrepancy.refit import Refit, refine, refit
from BreastBiomechLib.discrepancy.regions import regions_of
from BreastBiomechLib.discrepancy.sensitivity import Sensitivities, sensitivities
from BreastBiomechLib.discrepancy.state import ModelState

VERDICTS = ("missing effect", "ambiguous", "unexplained discrepancy", "no significant discrepancy")
EDGE = 0.005  # a fitted parameter this close to an end of its range (unit coordinates) is at it
ABSORBED = 0.8  # a candidate this much of whose signature the fitted parameters reproduce is hard to see


@dataclass
class DiagnosisSettings:
    """Decision thresholds: ``alpha`` the family-wise significance level, ``refit_top`` how many
    significant candidates are refitted, ``min_explained`` the share of the residual (whitened
    sum of squares) a named effect's refit must remove beyond the same refit of the fitted
    parameters alone, ``bic_threshold`` the largest dBIC against that nested refit that confirms
    (-10: very strong evidence, Kass and Raftery), ``ambiguity_correlation`` and ``ambiguity_bic`` when two
    confirmed candidates cannot be told apart, ``min_localisation`` the overlap of residual and
    signature over the regions a candidate needs; ``refine_iterations`` the Gauss-Newton
    iterations of the refit of the effect that is added."""

    alpha: float = 0.01
    refit_top: int = 3
    min_explained: float = 0.4
    bic_threshold: float = -10.0
    ambiguity_correlation: float = 0.9
    ambiguity_bic: float = 6.0
    min_localisation: float = 0.5
    refine_iterations: int = 2


@dataclass
class Candidate:
    """One candidate's evidence: its score test (``statistic``, ``dof``, ``p_value``, the
    Bonferroni-corrected ``p_adjusted``), the share of the residual its signature could explain
    (``explained_fraction``), the linearised ``estimate`` and its ``sd``, where its signature
    sits (``signature_regions``: share per region), the ``localisation`` overlap, and after a
    refit the LR test and dBIC against the refit of the fitted parameters alone (the nested null
    model, stepped the same way), the share of that refit's residual it removed and the values it
    refitted to; ``absorbed`` the share of its signature the fitted parameters reproduce
    (:func:`~BreastBiomechLib.discrepancy.statistics.absorbed_share`) and ``absorbed_by`` the
    fitted parameter that alone reproduces most of it ({"name", "correlation"}); or the reason
    it was ``skipped``."""

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
    it) and ``edges`` the fit's parameters at an end of their range."""

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

    def to_dict(self) -> dict:
        return {"verdict": self.verdict, "effect": self.effect, "alternatives": self.alternatives,
                "sentence": self.sentence, "overall": self.overall, "held": self.held, "edges": self.edges,
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


def absorbed_sentence(candidates: list[Candidate]) -> str:
    """The tested candidates whose signature the fitted parameters reproduce (at least
    :data:`ABSORBED` of it), as a sentence ("" when none)."""
    hidden = [c for c in candidates if not c.skipped and c.absorbed >= ABSORBED]
    if not hidden:
        return ""
    listed = "; ".join(f"{c.title} ({c.absorbed:.0%} of its signature, chiefly by {c.absorbed_by['name']}, "
                       f"correlation {c.absorbed_by['correlation']:.2f})" for c in hidden)
    return (f"Hard to see at this fit, since the fitted parameters reproduce what it would change: {listed}; "
            "such an effect, if present, has been fitted as those parameters.")


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
          refits: dict[str, Refit], iterations: int, progress: Callable[[str], None] | None = None) -> Refit:
    """The refit of ``state`` with ``candidate``'s ``effect`` added, refined by ``iterations``
    Gauss-Newton iterations of every fitted parameter (warm start: its confirmation refit in
    ``refits``, else one made now from the round's sensitivities ``sens``). Records the refined
    values in ``candidate.refit``; 0 iterations keep the confirmation refit as it is."""
    say = progress or (lambda message: None)
    chosen = refits.get(candidate.name)
    if chosen is None:
        say(f"refitting with {candidate.name}")
        made = refit(state, observations, sens, [effect])
        if not made or not made[0].ok:
            raise RuntimeError(f"{candidate.title}: no refit with it solves ({made[0].status if made else 'not built'}); "
                               "it cannot be added to this model")
        chosen = refits[candidate.name] = made[0]
    if iterations > 0:
        say(f"refining the refit with {candidate.name}")
        refined, outcome = refine(chosen.state, observations, iterations, say)
        weights = 1.0 / observations.sigma
        after = observations.residual(outcome.displacement)
        chosen = replace(chosen, values=refined.added[candidate.name][1], state=refined,
                         displacement=outcome.displacement, residual_after=after,
                         rss_after=float(np.sum((weights * after) ** 2)))
    candidate.refit = candidate.refit or {"status": chosen.status, "values": chosen.values.tolist(),
                                          "sd": chosen.sd.tolist(), "described": chosen.effect.describe(chosen.values),
                                          "rss_before": chosen.rss_before, "rss_after": chosen.rss_after}
    candidate.refit.update({"refined_values": chosen.values.tolist(),
                            "refined_described": chosen.effect.describe(chosen.values),
                            "rss_refined": chosen.rss_after,
                            "refine_iterations": candidate.refit.get("refine_iterations", 0) + iterations})
    return chosen


def diagnose(state: ModelState, observations: Observations, candidates: list[Effect],
             settings: DiagnosisSettings | None = None,
             progress: Callable[[str], None] | None = None, excluded: dict[str, str] | None = None) -> Diagnosis:
    """One round of the diagnosis of ``state`` against ``observations`` over ``candidates``
    (the library's effects; those already added, unavailable or ``excluded`` ({name: reason},
    e.g. rejected by the user) are reported as skipped). The fit's parameters at an end of their
    range are listed in ``edges`` and said after the verdict's sentence."""
    result = _decide(state, observations, candidates, settings, progress, excluded)
    result.edges = parameters_at_edges(state, result.held)
    hidden = absorbed_sentence(result.candidates) if result.verdict != "missing effect" else ""
    if hidden:
        result.sentence = f"{result.sentence} {hidden}"
    if result.edges:
        result.sentence = f"{result.sentence} {edges_sentence(result.edges)}"
    return result


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
                  or effect.unavailable(fitted))
        if reason:
            skipped[effect.name] = reason
        else:
            testable.append(effect)
    sens = sensitivities(state, observations, testable, say)
    sens.skipped = {**skipped, **sens.skipped}
    weights = 1.0 / observations.sigma
    residual = observations.measured - sens.features
    whitened = weights * residual
    nuisance = weights[:, None] * sens.nuisance
    held = statistics.pushed_out(nuisance, whitened, *ends_of_range(state))
    q_theta = statistics.basis(nuisance[:, ~held])
    overall = statistics.overall(whitened, q_theta)
    feature_regions = regions_of(fitted, observations.points, sens.displacement)
    excess = whitened ** 2 - 1.0
    residual_shares = _shares(excess, feature_regions)
    tested = [e for e in testable if e.name in sens.effects]
    m = max(len(tested), 1)
    ranked: list[Candidate] = []
    for effect in tested:
        b = weights[:, None] * sens.effects[effect.name]
        test = statistics.score_test(whitened, q_theta, b)
        change = (b @ np.atleast_1d(test["estimate"])) ** 2
        signature = _shares(change, feature_regions)
        overlap = float(sum(min(signature.get(k, 0.0), residual_shares.get(k, 0.0)) for k in residual_shares))
        ranked.append(Candidate(effect.name, effect.title, effect.acts_in, test["statistic"], test["dof"],
                                test["p_value"], min(1.0, test["p_value"] * m), test["explained_fraction"],
                                np.atleast_1d(test["estimate"]).tolist(), np.atleast_1d(test["sd"]).tolist(),
                                signature, overlap, absorbed=statistics.absorbed_share(b, q_theta),
                                absorbed_by=_absorbed_by(b, nuisance, held, sens.nuisance_keys)))
    ranked.sort(key=lambda c: (c.p_value, -c.statistic))
    for name, reason in sens.skipped.items():
        effect = next((e for e in candidates if e.name == name), None)
        ranked.append(Candidate(name, effect.title if effect else name, effect.acts_in if effect else "",
                                skipped=reason))
    correlations = {}
    for i, a in enumerate(tested):
        for b in tested[i + 1:]:
            correlations[f"{a.name}|{b.name}"] = statistics.canonical_correlation(
                weights[:, None] * sens.effects[a.name], weights[:, None] * sens.effects[b.name], q_theta)
    significant = overall["p_value"] < settings.alpha or any(c.p_adjusted < settings.alpha for c in ranked
                                                            if not c.skipped)
    regions = region_summary(observations, residual, feature_regions)
    base = dict(overall=overall, candidates=ranked, regions=regions, correlations=correlations,
                sensitivities=sens, feature_regions=feature_regions, refits={},
                held=[key for key, h in zip(sens.nuisance_keys, held) if h])
    if not significant:
        return Diagnosis("no significant discrepancy", None, [],
                         f"No significant discrepancy: the residual is what the noise model expects "
                         f"(T = {overall['statistic']:.1f} on {overall['dof']} degrees of freedom, p = "
                         f"{overall['p_value']:.3g}) and no candidate's score test is significant.", refitted=None,
                         **base)
    chosen = [c for c in ranked if not c.skipped and c.p_adjusted < settings.alpha][:settings.refit_top]
    by_name = {e.name: e for e in tested}
    say(f"refitting {', '.join(c.name for c in chosen) or 'no candidate'}")
    made = refit(state, observations, sens, [by_name[c.name] for c in chosen] + [None])
    refits = {r.effect.name: r for r in made if r.effect is not None}
    base["refits"] = refits
    # the nested null model refitted by the same step: what the fitted parameters alone remove
    fitted_only = next((r for r in made if r.effect is None and r.ok), None)
    rss_null = min(fitted_only.rss_after, fitted_only.rss_before) if fitted_only else None
    n = len(observations)
    confirmed = []
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
                           "removed": max(null - r.rss_after, 0.0) / null if null > 0 else 0.0,
                           "excess_explained": statistics.excess_explained(null, r.rss_after, overall["dof"],
                                                                           overall["dof"] - k)}
        if r.note:
            candidate.refit["note"] = r.note
        if (r.ok and lr["p_value"] * m < settings.alpha and lr["delta_bic"] <= settings.bic_threshold
                and candidate.localisation >= settings.min_localisation):
            confirmed.append(candidate)
    if not confirmed:
        tried = ", ".join(f"{c.name} (dBIC {c.refit.get('delta_bic', float('nan')):.1f}, localisation "
                          f"{c.localisation:.2f})" for c in chosen if c.refit) or "none was significant alone"
        alone = 1.0 - rss_null / fitted_only.rss_before if fitted_only and fitted_only.rss_before > 0 else 0.0
        hint = (f" Refitting the fitted parameters alone removes {alone:.0%} of it: the fit has not converged on "
                "these features (landmarks and surface); refit with them before diagnosing."
                if alone >= settings.min_explained else "")
        return Diagnosis("unexplained discrepancy", None, [],
                         f"Unexplained discrepancy: the residual is significant (T = {overall['statistic']:.1f} on "
                         f"{overall['dof']} dof, p = {overall['p_value']:.3g}) but no candidate effect explains it "
                         f"(refitted: {tried}).{hint}", refitted=None, **base)
    confirmed.sort(key=lambda c: c.refit["delta_bic"])
    best = confirmed[0]
    if best.refit["removed"] < settings.min_explained:
        return Diagnosis("unexplained discrepancy", None, [best.name],
                         f"Unexplained discrepancy: the best candidate, {best.title}, removes only "
                         f"{best.refit['removed']:.0%} of the residual beyond the fitted parameters alone "
                         f"(dBIC {best.refit['delta_bic']:.1f}); something the library does not hold is missing.",
                         refitted=None, **base)
    rivals = [c for c in confirmed[1:]
              if c.refit["delta_bic"] - best.refit["delta_bic"] < settings.ambiguity_bic
              and correlations.get(f"{best.name}|{c.name}", correlations.get(f"{c.name}|{best.name}", 0.0))
              >= settings.ambiguity_correlation]
    if rivals:
        pair = " or ".join([best.title] + [c.title for c in rivals])
        corr = max(correlations.get(f"{best.name}|{c.name}", correlations.get(f"{c.name}|{best.name}", 0.0))
                   for c in rivals)
        return Diagnosis("ambiguous", None, [best.name] + [c.name for c in rivals],
                         f"Ambiguous: {pair}. Their signatures correlate {corr:.2f} after the fitted parameters are "
                         f"profiled out, and their refits differ by {rivals[0].refit['delta_bic'] - best.refit['delta_bic']:.1f} "
                         "in BIC; the data cannot tell them apart.", refitted=None, **base)
    chosen_refit = adopt(state, observations, sens, best, by_name[best.name], refits, settings.refine_iterations, say)
    return Diagnosis("missing effect", best.name, [],
                     f"Missing effect: {best.title} ({best.refit['refined_described']}). Score test p = "
                     f"{best.p_adjusted:.2g} (corrected), refit dBIC {best.refit['delta_bic']:.1f}, removing "
                     f"{best.refit['removed']:.0%} of the residual beyond the fitted parameters alone; its signature "
                     f"and the residual overlap "
                     f"{best.localisation:.0%} over the regions ({best.acts_in}).{_bound_note(chosen_refit)}",
                     refitted=chosen_refit, **base)


def _bound_note(chosen: Refit) -> str:
    """A sentence on the added effect's parameters that its refit left within :data:`EDGE` of
    an end of their range ("" when none): their value is a bound the data press against, not an
    estimate (friction beyond sticking, for one, changes nothing)."""
    ends = []
    for parameter, value in zip(chosen.effect.parameters, chosen.values):
        end = range_end(value, parameter.lower, parameter.upper)
        if end:
            unit = f" {parameter.unit}" if parameter.unit else ""
            ends.append(f"{parameter.name} at the {end} of its range ({value:.4g}{unit})")
    if not ends:
        return ""
    return (f" Refitted to an end of its range: {', '.join(ends)}; the value is a bound the data press against, "
            "not an estimate (its range is where the effect stays physical, or beyond it nothing changes).")
