"""The statistics of the diagnosis, on whitened quantities (each feature divided by its noise).

Linearised at the current model: residual r = J_theta d_theta + J_phi phi + noise, noise
N(0, I) after whitening, theta the parameters already fitted (nuisance), phi a candidate
effect's parameters (0 in the current model, the nested case).

- Overall discrepancy: T = |P r|^2 with P the projection off span(J_theta); chi-square with
  n - rank(J_theta) degrees of freedom when nothing is missing.
- Per channel (landmarks, surface): the same test on the channel's features alone, its own
  projection off the span of J_theta's rows of that channel. Features are independent, so the
  channels' statistics are independent chi-squares under "nothing is missing", each valid by
  itself; a channel of 60 features is not drowned by one of 300 as in the pooled sum. The
  family (the pooled test and each channel's) is combined by Bonferroni: p = family size times
  the smallest p. The score tests are combined the same way (``score_by_channel``).
- Rao's score (Lagrange-multiplier) test of a candidate: S = g' I^-1 g with g = B' P r and
  I = B' B, B = P J_phi (the efficient information, theta profiled out): chi-square with rank(B)
  degrees of freedom under "the effect is absent". Needs only the model at the current fit and
  each candidate's sensitivity, so every candidate is tested from one batch of solves.
- Likelihood-ratio test and BIC of a refit: with the noise known, -2 log L = |r|^2, so
  LR = |r0|^2 - |r1|^2 (chi-square, k dof) and dBIC = |r1|^2 - |r0|^2 + k ln n.
- How alike two candidates' signatures are: the largest canonical correlation of their
  projected sensitivities (1: the data cannot tell them apart).
- How much of a candidate's signature the fitted parameters reproduce (``absorbed_share``): the
  share of its squared norm inside span(J_theta). Near 1 the fit has taken the effect up (a
  held chest wall fitted as a stiffer pectoral muscle) and no test of the residual can see it.
- The smallest size of an effect its score test would see (``minimum_detectable``): with the
  effect present at phi the statistic is a noncentral chi-square with noncentrality |B phi|^2,
  so the size along each parameter at which the test reaches its level with a given power is
  sqrt(lambda*) / |B e_j|, lambda* the noncentrality of that power.
- A fitted parameter held at a bound of its range, where the data push it further out (its
  residual gradient points out of the range), cannot move to absorb anything: it is fixed
  (an active constraint) and left out of J_theta (``pushed_out``).
"""

from __future__ import annotations

import numpy as np
from scipy import stats

RANK_TOLERANCE = 1e-8


def basis(matrix: np.ndarray, scale: float | None = None) -> np.ndarray:
    """An orthonormal basis (n, r) of the column space of ``matrix`` (n, k), leaving out
    directions whose singular value is below :data:`RANK_TOLERANCE` times ``scale`` (default the
    largest singular value; give the norm of what ``matrix`` was projected from, so that what
    a projection left as round-off does not count)."""
    if matrix.size == 0:
        return np.zeros((matrix.shape[0], 0))
    u, s, _ = np.linalg.svd(matrix, full_matrices=False)
    reference = s.max(initial=0.0) if scale is None else scale
    return u[:, s > RANK_TOLERANCE * max(reference, 1e-300)]


def project_off(vectors: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``vectors`` (n,) or (n, k) with their components in the span of the orthonormal ``q`` removed."""
    return vectors - q @ (q.T @ vectors)


def overall(residual: np.ndarray, q_theta: np.ndarray) -> dict:
    """The overall discrepancy test: T, degrees of freedom, p-value, and T per degree of freedom."""
    t = float(np.sum(project_off(residual, q_theta) ** 2))
    dof = max(len(residual) - q_theta.shape[1], 1)
    return {"statistic": t, "dof": dof, "p_value": float(stats.chi2.sf(t, dof)), "per_dof": t / dof}


def channel_family(pooled: dict, tests: dict[str, dict]) -> dict:
    """The pooled test's numbers with each channel's (``tests``: {channel: test}) under
    "channels", and the family's Bonferroni-combined p-value ("p_combined": the number of tests
    times the smallest p, at most 1; the pooled p alone where no channel has its own test)."""
    family = [pooled["p_value"]] + [t["p_value"] for t in tests.values()]
    return {**pooled, "channels": tests, "family": len(family),
            "p_combined": float(min(1.0, len(family) * min(family)))}


def _channel_rows(channels, needed: int):
    """{channel: boolean rows} of every channel name in ``channels`` (n,) with more than
    ``needed`` features; {} where there is only one channel (the pooled test is its test)."""
    channels = np.asarray(channels)
    names = sorted(set(channels.tolist()))
    if len(names) < 2:
        return {}
    return {name: channels == name for name in names if int((channels == name).sum()) > needed}


def overall_by_channel(residual: np.ndarray, nuisance: np.ndarray, channels) -> dict:
    """The overall test of the whitened ``residual`` (n,) against the whitened ``nuisance``
    sensitivities (n, p) pooled and per channel (``channels`` (n,) names), combined by
    :func:`channel_family`; each channel's test also gives its "features"."""
    pooled = overall(residual, basis(nuisance))
    tests = {}
    for name, rows in _channel_rows(channels, nuisance.shape[1]).items():
        q = basis(nuisance[rows])
        if int(rows.sum()) > q.shape[1]:
            tests[name] = overall(residual[rows], q) | {"features": int(rows.sum())}
    return channel_family(pooled, tests)


def score_by_channel(residual: np.ndarray, nuisance: np.ndarray, sensitivity: np.ndarray, channels) -> dict:
    """A candidate's score test (:func:`score_test`; the estimate and explained fraction are the
    pooled test's) with each channel's own (its rows of ``residual``, ``nuisance`` and
    ``sensitivity``), combined by :func:`channel_family`."""
    pooled = score_test(residual, basis(nuisance), sensitivity)
    sensitivity = np.atleast_2d(sensitivity.T).T
    tests = {}
    for name, rows in _channel_rows(channels, nuisance.shape[1]).items():
        test = score_test(residual[rows], basis(nuisance[rows]), sensitivity[rows])
        if test["dof"]:
            tests[name] = {"statistic": test["statistic"], "dof": test["dof"], "p_value": test["p_value"]}
    return channel_family(pooled, tests)


def score_test(residual: np.ndarray, q_theta: np.ndarray, sensitivity: np.ndarray) -> dict:
    """Rao's score test of a candidate with whitened ``sensitivity`` (n, k): the statistic, its
    degrees of freedom (the rank of the projected sensitivity), p-value, the linearised estimate
    of its parameters (k,) with their standard deviations, and the fraction of the projected
    residual's squared norm it explains."""
    r = project_off(residual, q_theta)
    original = np.atleast_2d(sensitivity.T).T
    b = project_off(original, q_theta)
    q_b = basis(b, np.linalg.norm(original, 2))
    dof = q_b.shape[1]
    explained = q_b.T @ r
    s = float(explained @ explained)
    information = b.T @ b
    covariance = np.linalg.pinv(information, rcond=1e-12) if dof else np.zeros_like(information)
    estimate = covariance @ (b.T @ r)
    total = float(r @ r)
    return {"statistic": s, "dof": dof, "p_value": float(stats.chi2.sf(s, dof)) if dof else 1.0,
            "estimate": estimate, "sd": np.sqrt(np.maximum(np.diag(covariance), 0.0)),
            "explained_fraction": s / total if total > 0 else 0.0}


def canonical_correlation(a: np.ndarray, b: np.ndarray, q_theta: np.ndarray) -> float:
    """The largest canonical correlation between the projected column spaces of ``a`` and ``b``
    (whitened sensitivities (n, ka), (n, kb)); 0 when either is empty."""
    a, b = np.atleast_2d(a.T).T, np.atleast_2d(b.T).T
    qa = basis(project_off(a, q_theta), np.linalg.norm(a, 2))
    qb = basis(project_off(b, q_theta), np.linalg.norm(b, 2))
    if qa.shape[1] == 0 or qb.shape[1] == 0:
        return 0.0
    return float(min(np.linalg.svd(qa.T @ qb, compute_uv=False).max(), 1.0))


def detectable_noncentrality(dof: int, alpha: float, power: float = 0.8, least_statistic: float = 0.0) -> float:
    """The noncentrality lambda at which a chi-square test of ``dof`` degrees of freedom at level
    ``alpha`` - and its statistic at least ``least_statistic``, where a verdict asks more of it
    (a BIC threshold) - rejects with probability ``power`` (inf without degrees of freedom)."""
    from scipy.optimize import brentq

    if dof < 1:
        return float("inf")
    critical = max(stats.chi2.isf(alpha, dof), least_statistic)
    reach = lambda lam: stats.ncx2.sf(critical, dof, lam) - power  # noqa: E731
    high = 1.0
    while reach(high) < 0:
        high *= 2.0
    return float(brentq(reach, 0.0, high, xtol=1e-10))


def minimum_detectable(sensitivity: np.ndarray, q_theta: np.ndarray, alpha: float, power: float = 0.8,
                       least_statistic: float = 0.0) -> np.ndarray:
    """The smallest size (k,) of each of a candidate's parameters, in the units of its whitened
    ``sensitivity`` (n, k) (per unit of the parameter), at which its score test - the signature
    projected off span(``q_theta``), the fitted parameters profiled out - reaches level ``alpha``
    (and a statistic of ``least_statistic``) with ``power``, the other parameters at their off
    values (inf where the projected signature is zero: the fitted parameters take the effect up
    whole)."""
    b = project_off(np.atleast_2d(sensitivity.T).T, q_theta)
    original = np.atleast_2d(sensitivity.T).T
    dof = basis(b, np.linalg.norm(original, 2)).shape[1]
    lam = detectable_noncentrality(dof, alpha, power, least_statistic)
    norms = np.linalg.norm(b, axis=0)
    with np.errstate(divide="ignore"):
        return np.where(norms > RANK_TOLERANCE * max(np.linalg.norm(original), 1e-300), np.sqrt(lam) / norms, np.inf)


def absorbed_share(sensitivity: np.ndarray, q_theta: np.ndarray) -> float:
    """The share (0-1) of the whitened ``sensitivity`` (n,) or (n, k)'s squared norm inside the
    span of the orthonormal ``q_theta``: how much of the candidate's signature the fitted
    parameters reproduce (0 when the sensitivity is zero)."""
    b = np.atleast_2d(sensitivity.T).T
    total = float(np.sum(b ** 2))
    if total <= 0:
        return 0.0
    return float(np.clip(np.sum((q_theta.T @ b) ** 2) / total, 0.0, 1.0))


def pushed_out(nuisance: np.ndarray, residual: np.ndarray, at_top: np.ndarray, at_bottom: np.ndarray) -> np.ndarray:
    """Which nuisance parameters (whitened sensitivities ``nuisance`` (n, p), whitened
    ``residual`` (n,)) are at an end of their range (boolean ``at_top`` / ``at_bottom`` (p,))
    with the residual asking for more in that direction: moving the parameter up by d changes
    |r|^2 by -2 d J_k'r, so at the top J_k'r > 0 asks for more, at the bottom J_k'r < 0."""
    gradient = nuisance.T @ residual
    return (np.asarray(at_top) & (gradient > 0)) | (np.asarray(at_bottom) & (gradient < 0))


def likelihood_ratio(rss_before: float, rss_after: float, k: int, n: int) -> dict:
    """LR statistic, its p-value (chi-square, ``k`` dof) and dBIC of a refit that adds ``k``
    parameters and changes the whitened residual sum of squares from ``rss_before`` to
    ``rss_after`` on ``n`` features."""
    lr = rss_before - rss_after
    return {"statistic": float(lr), "p_value": float(stats.chi2.sf(max(lr, 0.0), k)) if k else 1.0,
            "delta_bic": float(rss_after - rss_before + k * np.log(n))}


def excess_explained(rss_before: float, rss_after: float, dof_before: int, dof_after: int) -> float:
    """The share of the residual's excess over its noise expectation that a refit removed:
    1 - max(rss_after - dof_after, 0) / (rss_before - dof_before) (0 when there was no excess)."""
    excess = rss_before - dof_before
    if excess <= 0:
        return 0.0
    return float(np.clip(1.0 - max(rss_after - dof_after, 0.0) / excess, 0.0, 1.0))
