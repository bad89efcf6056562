"""The diagnosis's statistics against their distributions: the score test and the overall test
are chi-square under "nothing missing" (Monte Carlo), the score test finds an effect of known
size, and the linear pieces (projection, canonical correlation, explained excess) are exact."""

from __future__ import annotations

import numpy as np
from scipy import stats

from BreastBiomechLib.discrepancy import statistics


def _design(rng, n=200, p=3, k=2):
    return rng.standard_normal((n, p)), rng.standard_normal((n, k))


def test_score_and_overall_tests_are_chi_square_when_nothing_is_missing():
    """Residuals of pure noise plus anything the nuisance explains: S ~ chi2(k), T ~ chi2(n - p);
    the rejection rate at 5 % is 5 % within Monte Carlo error (2000 draws: sd 0.5 %)."""
    rng = np.random.default_rng(1)
    a, b = _design(rng)
    q = statistics.basis(a)
    scores, totals = [], []
    for _ in range(2000):
        r = rng.standard_normal(200) + a @ rng.standard_normal(3)  # the nuisance part is profiled out
        test = statistics.score_test(r, q, b)
        assert test["dof"] == 2
        scores.append(test["p_value"])
        totals.append(statistics.overall(r, q)["p_value"])
    assert abs(np.mean(np.array(scores) < 0.05) - 0.05) < 0.015
    assert abs(np.mean(np.array(totals) < 0.05) - 0.05) < 0.015
    assert stats.kstest(scores, "uniform").pvalue > 0.01


def test_score_test_finds_an_effect_and_estimates_its_size():
    """r = B phi + noise: the estimate is phi within its standard deviation (3 sd), the test
    rejects, and it explains most of the residual's excess."""
    rng = np.random.default_rng(2)
    a, b = _design(rng, n=400)
    phi = np.array([0.4, -0.25])
    q = statistics.basis(a)
    r = b @ phi + rng.standard_normal(400)
    test = statistics.score_test(r, q, b)
    assert test["p_value"] < 1e-6
    assert np.all(np.abs(test["estimate"] - phi) < 3 * test["sd"])
    np.testing.assert_allclose(test["sd"], np.sqrt(np.diag(np.linalg.inv(statistics.project_off(b, q).T
                                                                         @ statistics.project_off(b, q)))))


def test_a_signature_the_nuisance_already_spans_has_no_score():
    """An effect whose sensitivity is a combination of the fitted parameters' cannot be seen: zero
    degrees of freedom, p = 1."""
    rng = np.random.default_rng(3)
    a, _ = _design(rng)
    test = statistics.score_test(rng.standard_normal(200), statistics.basis(a), a @ np.array([1.0, -2.0, 0.5]))
    assert test["dof"] == 0 and test["p_value"] == 1.0


def test_canonical_correlation():
    rng = np.random.default_rng(4)
    a, b = _design(rng, k=1)
    q = statistics.basis(a)
    assert statistics.canonical_correlation(b, 3 * b, q) > 1 - 1e-9
    other = rng.standard_normal((200, 1))
    assert statistics.canonical_correlation(b, other, q) < 0.3
    # alike once the nuisance is profiled out: b and b plus a nuisance direction
    assert statistics.canonical_correlation(b, b + a[:, :1], q) > 1 - 1e-9


def test_likelihood_ratio_bic_and_excess():
    lr = statistics.likelihood_ratio(300.0, 180.0, 2, 200)
    assert lr["statistic"] == 120.0
    assert lr["delta_bic"] == -120.0 + 2 * np.log(200)
    assert lr["p_value"] == stats.chi2.sf(120.0, 2)
    assert statistics.excess_explained(300.0, 198.0, 197, 195) == 1 - 3.0 / 103.0
    assert statistics.excess_explained(150.0, 140.0, 197, 195) == 0.0  # no excess to explain
