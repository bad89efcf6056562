"""From a round's numbers to its verdict and the sentence that says it (no solves here: the
numbers come from :mod:`~BreastBiomechLib.discrepancy.diagnosis`).

The rules (thresholds in :class:`~BreastBiomechLib.discrepancy.diagnosis.DiagnosisSettings`):

- The **overall** test is the family of the pooled test and each channel's own
  (:func:`~BreastBiomechLib.discrepancy.statistics.overall_by_channel`), Bonferroni-combined; a
  candidate's **score test** likewise, and Bonferroni-corrected over the candidates tested.
- **No significant discrepancy** when neither the overall test nor any candidate's score test is
  significant at ``alpha``.
- A candidate is **confirmed** when its refit is solved, its likelihood-ratio test is significant
  (corrected), its dBIC against the refit of the fitted parameters alone is at most
  ``bic_threshold``, the residual's excess sits where its signature does (``localisation``) and
  the refit changes the features by a size that matters: the RMS of the largest tenth of the
  feature changes (``effect_mm``) at least ``min_effect`` times the model-error floor of those
  features (``floor_mm``: measured per feature where the floor was measured).
- **Missing effect** X when the confirmed candidate with the lowest dBIC removes at least
  ``min_explained`` of the residual beyond the fitted parameters alone; **ambiguous** when a
  second confirmed one is within ``ambiguity_bic`` of it and their signatures correlate at least
  ``ambiguity_correlation``.
- Otherwise **unexplained discrepancy** only when the overall test is significant: the residual
  exceeds what the noise model (with its model-error floor) expects. Where only directed score
  tests were significant and their refits did not hold up, the residual is at the level of the
  floor: **no significant discrepancy**, and the sentence says what residual remains and where.

Every sentence is written by one function from the numbers it quotes, so that what a sentence
says about significance is what its numbers show.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

NONE = "no significant discrepancy"
UNEXPLAINED = "unexplained discrepancy"
MISSING = "missing effect"
AMBIGUOUS = "ambiguous"
VERDICTS = (MISSING, AMBIGUOUS, UNEXPLAINED, NONE)
EFFECT_QUANTILE = 0.9  # an effect's size: the RMS of the feature changes above this quantile (where it acts)


def where_it_acts(change: np.ndarray) -> np.ndarray:
    """The features (boolean (n,)) where a refit's ``change`` (n,) mm is largest: at or above the
    :data:`EFFECT_QUANTILE` quantile of its magnitude."""
    size = np.abs(np.asarray(change, float))
    if size.size == 0:
        return np.zeros(0, bool)
    return size >= np.quantile(size, EFFECT_QUANTILE)


def effect_size_mm(change: np.ndarray) -> float:
    """The size of a refit's change of the features (mm): the RMS of the changes where it acts
    (:func:`where_it_acts`; an effect confined to a contact band is not diluted by the features
    it leaves alone)."""
    change = np.asarray(change, float)
    acts = where_it_acts(change)
    return float(np.sqrt(np.mean(change[acts] ** 2))) if acts.any() else 0.0


def floor_ratio(change: np.ndarray, floor_mm: np.ndarray, factor: float = 1.0) -> float:
    """A change of the features (``change`` (n,) mm) against the model-error floor where it acts
    (``floor_mm`` (n,) mm per feature): its size (:func:`effect_size_mm`) over ``factor`` times
    the floor's RMS on the same features. Below 1 the model's own error could make such a change,
    so it does not matter (the rule a named effect must pass, and what an estimate's interval
    takes in); infinite where there is no floor."""
    change = np.asarray(change, float)
    acts = where_it_acts(change)
    floor = float(np.sqrt(np.mean(np.asarray(floor_mm, float)[acts] ** 2))) if acts.any() else 0.0
    size = effect_size_mm(change)
    return size / (factor * floor) if factor * floor > 0 else (0.0 if size == 0 else float("inf"))


@dataclass
class Evidence:
    """What a round's verdict is decided from: the ``overall`` test (pooled numbers with
    "channels" and "p_combined"), the ``candidates`` (dicts of
    :meth:`~BreastBiomechLib.discrepancy.diagnosis.Candidate.to_dict`'s keys, ranked, refit
    records filled where refitted), the pairwise ``correlations`` of their signatures
    ({"a|b": value}), the residual's RMS (``residual_rms_mm``) and where it is largest
    (``largest_region``, e.g. "contact 1 (surface)"), the model-error floor ``floor_mm``,
    the share of the residual the refit of the fitted parameters alone removed
    (``fitted_alone_removed``; None when it was not refitted) and the landmarks' assumed
    localisation sd and model-error floor (``landmark_noise``, mm each; None without landmarks)."""

    overall: dict
    candidates: list[dict]
    correlations: dict = field(default_factory=dict)
    residual_rms_mm: float = 0.0
    largest_region: str = ""
    floor_mm: float = 0.0
    fitted_alone_removed: float | None = None
    landmark_noise: tuple[float, float] | None = None


@dataclass
class Decision:
    """A verdict (one of :data:`VERDICTS`), the ``effect`` it names (missing effect), the
    ``alternatives`` (ambiguous: all of them; unexplained: the nearest candidate) and the
    ``sentence`` (for a missing effect the caller writes it after the effect's refinement, with
    :func:`missing_effect_sentence`)."""

    verdict: str
    effect: str | None = None
    alternatives: list[str] = field(default_factory=list)
    sentence: str = ""


def tested(evidence: Evidence) -> list[dict]:
    return [c for c in evidence.candidates if not c.get("skipped")]


def significant_candidates(evidence: Evidence, alpha: float) -> list[dict]:
    """The tested candidates whose corrected score test is significant, in the evidence's order."""
    return [c for c in tested(evidence) if c["p_adjusted"] < alpha]


def overall_significant(evidence: Evidence, alpha: float) -> bool:
    return evidence.overall.get("p_combined", evidence.overall["p_value"]) < alpha


def confirmation(candidate: dict, settings, floor_mm: float) -> list[str]:
    """The confirmation rules a refitted ``candidate`` fails, as short phrases ([] when confirmed)."""
    refit = candidate.get("refit") or {}
    if refit.get("status") != "completed" or "delta_bic" not in refit:
        return [f"its refit {refit.get('status', 'was not made')}"]
    failed = []
    if not refit["lr_p_adjusted"] < settings.alpha:
        failed.append(f"LR p {refit['lr_p_adjusted']:.2g}")
    if not refit["delta_bic"] <= settings.bic_threshold:
        failed.append(f"dBIC {refit['delta_bic']:.1f} > {settings.bic_threshold:g}")
    if not candidate["localisation"] >= settings.min_localisation:
        failed.append(f"localisation {candidate['localisation']:.2f} < {settings.min_localisation:g}")
    needed = settings.min_effect * refit.get("floor_mm", floor_mm)  # the floor where it acts, where recorded
    if not refit.get("effect_mm", float("inf")) >= needed:
        failed.append(f"moves the features by {refit['effect_mm']:.2f} mm, below {needed:.2f} mm "
                      f"({settings.min_effect:g} x the model floor there)")
    return failed


def decide(evidence: Evidence, settings) -> Decision:
    """The verdict of ``evidence`` by the module's rules (the sentence of every verdict but a
    missing effect written here)."""
    alpha = settings.alpha
    directed = significant_candidates(evidence, alpha)
    if not overall_significant(evidence, alpha) and not directed:
        return Decision(NONE, sentence=quiet_sentence(evidence, alpha))
    refitted = [c for c in directed if c.get("refit")]
    confirmed = sorted((c for c in refitted if not confirmation(c, settings, evidence.floor_mm)),
                       key=lambda c: c["refit"]["delta_bic"])
    best = confirmed[0] if confirmed else None
    if best is not None and best["refit"]["removed"] >= settings.min_explained:
        rivals = [c for c in confirmed[1:]
                  if c["refit"]["delta_bic"] - best["refit"]["delta_bic"] < settings.ambiguity_bic
                  and correlation(evidence, best["name"], c["name"]) >= settings.ambiguity_correlation]
        if rivals:
            return Decision(AMBIGUOUS, None, [best["name"]] + [c["name"] for c in rivals],
                            ambiguous_sentence(evidence, best, rivals))
        return Decision(MISSING, best["name"])
    if not overall_significant(evidence, alpha):
        return Decision(NONE, sentence=floor_sentence(evidence, refitted, settings))
    nearest = max(refitted, key=lambda c: c["refit"].get("removed", 0.0), default=None)
    return Decision(UNEXPLAINED, None, [nearest["name"]] if nearest else [],
                    unexplained_sentence(evidence, refitted, best, settings))


def correlation(evidence: Evidence, a: str, b: str) -> float:
    return evidence.correlations.get(f"{a}|{b}", evidence.correlations.get(f"{b}|{a}", 0.0))


def overall_phrase(overall: dict) -> str:
    """Each channel's test, the pooled one and the combined p-value, as a phrase."""
    parts = [f"{name} T = {t['statistic']:.1f} on {t['dof']} dof, p = {t['p_value']:.3g}"
             for name, t in overall.get("channels", {}).items()]
    pooled = f"T = {overall['statistic']:.1f} on {overall['dof']} dof, p = {overall['p_value']:.3g}"
    if not parts:
        return pooled
    return "; ".join(parts + [f"all features {pooled}"]) + f"; combined p = {overall['p_combined']:.3g}"


def strongest_phrase(overall: dict) -> str:
    """The test of the family with the smallest p (a channel's or the pooled one) and the combined p."""
    tests = {"all features": overall, **overall.get("channels", {})}
    name, t = min(tests.items(), key=lambda item: item[1]["p_value"])
    text = f"{name}: T = {t['statistic']:.1f} on {t['dof']} dof, T/dof {t['statistic'] / max(t['dof'], 1):.2f}"
    return text + f", combined p = {overall.get('p_combined', overall['p_value']):.3g}"


def quiet_sentence(evidence: Evidence, alpha: float = 0.01) -> str:
    """No test significant; where a channel's residual is far below what the noise model expects
    (:func:`undersized_phrase`), said too."""
    ps = [c["p_adjusted"] for c in tested(evidence)]
    smallest = f" (smallest corrected p = {min(ps):.3g})" if ps else ""
    return (f"No significant discrepancy: the residual is within what the noise model allows "
            f"({overall_phrase(evidence.overall)}) and no candidate's score test is significant{smallest}."
            f"{undersized_phrase(evidence.overall, alpha)}")


def undersized_phrase(overall: dict, alpha: float = 0.01) -> str:
    """A sentence naming each channel (the pooled test where there are none) whose T is so far
    below its dof that noise of the assumed size would give a smaller T with probability under
    ``alpha`` (the lower tail of chi-square): the assumed noise and model floor are larger than
    this case's, so the tests could not see effects of about that size ("" where none is)."""
    from scipy.stats import chi2

    tests = overall.get("channels") or {"all features": overall}
    low = [(name, t) for name, t in tests.items() if t["dof"] > 0 and chi2.cdf(t["statistic"], t["dof"]) < alpha]
    if not low:
        return ""
    parts = ", ".join(f"{name} T/dof {t['statistic'] / t['dof']:.2g} "
                      f"(lower-tail p {chi2.cdf(t['statistic'], t['dof']):.1g})" for name, t in low)
    return (f" The residual is far smaller than the noise model assumes ({parts}): the assumed noise and model floor "
            "exceed this case's, so an effect smaller than they are could go unseen here.")


def _refit_phrase(candidate: dict, settings, floor_mm: float) -> str:
    refit = candidate["refit"]
    removed = f"removed {refit['removed']:.0%}" if "removed" in refit else "not solved"
    failed = confirmation(candidate, settings, floor_mm)
    return f"{candidate['name']} ({removed}" + (f"; {', '.join(failed)}" if failed else "") + ")"


def floor_sentence(evidence: Evidence, refitted: list[dict], settings) -> str:
    """Directed tests significant, the overall test not, no candidate holding up: a residual at
    the level of the model floor."""
    tried = "; ".join(_refit_phrase(c, settings, evidence.floor_mm) for c in refitted) or "none could be refitted"
    where = f", largest in {evidence.largest_region}" if evidence.largest_region else ""
    return (f"No significant discrepancy: a residual of {evidence.residual_rms_mm:.2f} mm RMS at the level of the "
            f"model floor ({evidence.floor_mm:.2f} mm) remains{where}. The overall test is not significant "
            f"({overall_phrase(evidence.overall)}); the directed score tests that were did not hold up when "
            f"refitted: {tried}.{_unconverged(evidence, settings)}")


def _unconverged(evidence: Evidence, settings) -> str:
    """A sentence where the refit of the fitted parameters alone removed at least
    ``min_explained`` of the residual ("" otherwise)."""
    alone = evidence.fitted_alone_removed
    if alone is None or alone < settings.min_explained:
        return ""
    return (f" Refitting the fitted parameters alone removes {alone:.0%} of it: the fit has not converged on "
            "these features (landmarks and surface); refit with them before diagnosing.")


def _needs(candidate: dict) -> str:
    """What a refitted candidate pressed against: its parameters at an end of their range."""
    ends = (candidate.get("refit") or {}).get("at_range_ends") or []
    return f", at the {ends[0]}" if len(ends) == 1 else (f", at the ends of its range ({'; '.join(ends)})" if ends else "")


def unexplained_sentence(evidence: Evidence, refitted: list[dict], best: dict | None, settings) -> str:
    """The overall test significant and no candidate explaining enough."""
    head = f"Unexplained discrepancy: the residual is significant ({strongest_phrase(evidence.overall)})"
    if best is not None:
        text = (f"{head}, and the best candidate, {best['title']}, removes only {best['refit']['removed']:.0%} of it "
                f"beyond the fitted parameters alone (dBIC {best['refit']['delta_bic']:.1f}); something the library "
                "does not hold is missing.")
    elif refitted:
        nearest = max(refitted, key=lambda c: c["refit"].get("removed", 0.0))
        tried = "; ".join(_refit_phrase(c, settings, evidence.floor_mm) for c in refitted)
        text = (f"{head}, but no candidate effect explains it (refitted: {tried}). Nearest: {nearest['title']}"
                f"{_needs(nearest)}.")
    else:
        text = (f"{head}, but no candidate's score test is significant: no effect of the library that this case "
                "could show would change it.")
    return text + landmarks_alone_phrase(evidence, settings.alpha) + _unconverged(evidence, settings)


def landmarks_alone_phrase(evidence: Evidence, alpha: float) -> str:
    """Where the landmarks' channel alone is significant (every other channel not), the other
    reading of an unexplained residual: landmarks marked less precisely than the noise model
    assumes. The localisation sd that would give their T/dof of 1 (with the same model-error
    floor), and what to do; "" otherwise."""
    channels = evidence.overall.get("channels") or {}
    marks = channels.get("landmarks")
    if marks is None or evidence.landmark_noise is None or not marks["dof"] or marks["p_value"] >= alpha:
        return ""
    if any(t["p_value"] < alpha for name, t in channels.items() if name != "landmarks"):
        return ""
    sd, floor = evidence.landmark_noise
    ratio = marks["statistic"] / marks["dof"]
    implied = float(np.sqrt(max(ratio * (sd ** 2 + floor ** 2) - floor ** 2, 0.0)))
    return (f" The landmarks alone carry it (T/dof {ratio:.2f}; the surface is within its noise): landmarks marked "
            f"with a localisation error of about {implied:.2g} mm rather than the assumed {sd:g} mm would read the "
            "same; if that is how precisely they were marked, give it (--landmark-sd-mm) and diagnose again.")


def ambiguous_sentence(evidence: Evidence, best: dict, rivals: list[dict]) -> str:
    pair = " or ".join([best["title"]] + [c["title"] for c in rivals])
    corr = max(correlation(evidence, best["name"], c["name"]) for c in rivals)
    return (f"Ambiguous: {pair}. Their signatures correlate {corr:.2f} after the fitted parameters are profiled out, "
            f"and their refits differ by {rivals[0]['refit']['delta_bic'] - best['refit']['delta_bic']:.1f} in BIC; "
            "the data cannot tell them apart.")


def interval_phrase(refit: dict, unsettled: bool = False) -> str:
    """"; 95 % interval 0.152 to 1.5 (...)" for a refit's record (its "interval", "interval_kind",
    "interval_open" and "data_interval"; "" without an interval): an end that reaches the
    parameter's range is said to be unbounded by the data there, and an interval the model-error
    floor widened gives the data's own beside it. Where the fit has not ``unsettled`` on the features
    (the fitted parameters alone remove a share of the residual), the interval is said to hold
    for the fitted materials as they are: it leaves out how far they are from their own best."""
    bounds = refit.get("interval")
    if not bounds:
        return ""
    opened = refit.get("interval_open") or [[False, False]] * len(bounds)
    data = refit.get("data_interval") or bounds
    parts = []
    for (lo, hi), (open_low, open_high), (data_lo, data_hi) in zip(bounds, opened, data):
        side = ("the data do not bound it" if open_low and open_high else
                "bounded by the data from below only" if open_high else
                "bounded by the data from above only" if open_low else "")
        widened = (f"the data alone {data_lo:.3g} to {data_hi:.3g}, the rest within the model-error floor"
                   if f"{data_lo:.3g} {data_hi:.3g}" != f"{lo:.3g} {hi:.3g}" else "")
        parts.append(f"{lo:.3g} to {hi:.3g}" + "".join(f", {note}" for note in (side, widened) if note))
    kind = refit.get("interval_kind", "linearised")
    given = ", given the fitted materials, which have not settled" if unsettled else ""
    return f"; 95 % {kind} interval {'; '.join(parts)}{given}"


def missing_effect_sentence(best: dict, bound_note: str = "", evidence: Evidence | None = None,
                            settings=None) -> str:
    """A confirmed candidate explaining enough, after its refinement (``best["refit"]`` holds
    "refined_described"). With the round's ``evidence`` and ``settings``: where the refit of the
    fitted parameters alone removed ``min_explained`` of the residual or more, the estimate's
    interval is said to be conditional on that unsettled fit, and the sentence ends saying so."""
    refit = best["refit"]
    unconverged = _unconverged(evidence, settings) if evidence is not None and settings is not None else ""
    within = interval_phrase(refit, unsettled=bool(unconverged))
    return (f"Missing effect: {best['title']} ({refit.get('refined_described', refit['described'])}{within}). "
            f"Score test p = "
            f"{best['p_adjusted']:.2g} (corrected), refit dBIC {refit['delta_bic']:.1f}, removing "
            f"{refit['removed']:.0%} of the residual beyond the fitted parameters alone and moving the features by "
            f"{refit['effect_mm']:.2f} mm where it acts; its signature and the residual overlap "
            f"{best['localisation']:.0%} over the regions ({best['acts_in']}).{bound_note}{unconverged}")
