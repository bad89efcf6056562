"""The diagnosis's statistics against their distributions: the score test and the overall test
are chi-square under "nothing missing" (Monte Carlo), the score test finds an effect of known
size, and the linear pieces (projection, canonical correlation, explained excess) are exact."""

from __future__ import annotations

import numpy as np
import pytest
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


def test_absorbed_share_is_the_part_of_a_signature_the_fitted_parameters_reproduce():
    rng = np.random.default_rng(5)
    a, b = _design(rng, k=1)
    q = statistics.basis(a)
    assert statistics.absorbed_share(a @ np.array([1.0, -2.0, 0.5]), q) > 1 - 1e-9
    other = statistics.project_off(b[:, 0], q)
    assert statistics.absorbed_share(other, q) < 1e-9
    mixed = other / np.linalg.norm(other) + a[:, 0] / np.linalg.norm(a[:, 0])  # half and half
    assert abs(statistics.absorbed_share(mixed, q) - 0.5) < 1e-9
    assert statistics.absorbed_share(np.zeros(200), q) == 0.0


def test_a_parameter_pushed_out_of_its_range_is_held_and_cannot_absorb_an_effect():
    """The effect's signature is the first fitted parameter's: profiled out with it, the effect
    has no score (dof 0). With that parameter at the top of its range and the residual asking
    for more of it, it is held there (pushed_out), and the score test finds the effect; asking
    for less, or at the bottom asking for more, it stays free."""
    rng = np.random.default_rng(6)
    a, _ = _design(rng)
    effect = a[:, 0]
    r = 0.4 * effect + rng.standard_normal(200)
    top, bottom = np.array([True, False, False]), np.array([False, False, False])
    assert statistics.score_test(r, statistics.basis(a), effect)["dof"] == 0
    held = statistics.pushed_out(a, r, top, bottom)
    assert held.tolist() == [True, False, False]
    test = statistics.score_test(r, statistics.basis(a[:, ~held]), effect)
    assert test["dof"] == 1 and test["p_value"] < 1e-6
    assert not statistics.pushed_out(a, -r, top, bottom).any()
    assert not statistics.pushed_out(a, r, bottom, top).any()
    assert statistics.pushed_out(a, -r, bottom, top).tolist() == [True, False, False]


def _channels(n_landmarks=60, n_surface=300):
    return np.array(["landmarks"] * n_landmarks + ["surface"] * n_surface)


def test_the_channels_combined_test_keeps_its_level_when_nothing_is_missing():
    """Pure noise plus anything the nuisance explains: each channel's own test is chi-square
    (rejection at 5 % within Monte Carlo error) and the Bonferroni-combined family rejects at
    most at its level (2000 draws; the family of three is conservative)."""
    rng = np.random.default_rng(5)
    channels = _channels()
    a, b = _design(rng, n=len(channels))
    landmark_p, combined, scores = [], [], []
    for _ in range(2000):
        r = rng.standard_normal(len(channels)) + a @ rng.standard_normal(3)
        test = statistics.overall_by_channel(r, a, channels)
        assert test["family"] == 3 and test["channels"]["landmarks"]["dof"] == 57
        landmark_p.append(test["channels"]["landmarks"]["p_value"])
        combined.append(test["p_combined"])
        scores.append(statistics.score_by_channel(r, a, b, channels)["p_combined"])
    assert abs(np.mean(np.array(landmark_p) < 0.05) - 0.05) < 0.015
    assert np.mean(np.array(combined) < 0.05) < 0.05 + 0.015
    assert np.mean(np.array(scores) < 0.05) < 0.05 + 0.015


def test_a_channel_of_few_features_is_not_drowned_by_one_of_many():
    """60 landmark features at 2.25 times the noise variance the model expects beside 300 surface features of
    pure noise (the issue's case: landmarks alone 1.9-6 times the expected per feature): the
    pooled test reads nothing, the landmarks' own test and the combined family do; the score test
    of a signature confined to the landmarks likewise."""
    rng = np.random.default_rng(6)
    channels = _channels()
    landmarks = channels == "landmarks"
    a, _ = _design(rng, n=len(channels))
    r = rng.standard_normal(len(channels)) * np.where(landmarks, 1.5, 1.0)
    test = statistics.overall_by_channel(r, a, channels)
    pooled_alone = statistics.overall(r, statistics.basis(a))
    assert test["p_value"] == pooled_alone["p_value"] and test["p_value"] > 0.05  # pooled: nothing
    assert test["channels"]["landmarks"]["p_value"] < 1e-4 and test["p_combined"] < 0.01
    assert test["p_combined"] == min(1.0, 3 * test["channels"]["landmarks"]["p_value"])
    single = statistics.overall_by_channel(r[landmarks], a[landmarks], channels[landmarks])
    assert single["channels"] == {} and single["family"] == 1 and single["p_combined"] == single["p_value"]
    signature = np.where(landmarks, rng.standard_normal(len(channels)), 0.0)[:, None]
    scored = statistics.score_by_channel(r + 0.6 * signature[:, 0], a, signature, channels)
    assert scored["channels"]["landmarks"]["p_value"] < scored["p_value"]
    assert "surface" not in scored["channels"]  # no signature there: no test of it


@pytest.mark.parametrize("k", [1, 2])
def test_an_effect_at_its_minimum_detectable_size_is_seen_four_times_in_five(k):
    """Calibration of ``minimum_detectable`` by simulation: a linear case (120 whitened features,
    4 fitted parameters, a candidate of k parameters) with the effect present at its reported
    smallest detectable size along one parameter: its score test reaches the level in 80 % of
    noise draws (within the simulation's error), at half that size in far fewer."""
    from BreastBiomechLib.discrepancy import statistics

    rng = np.random.default_rng(7)
    n, alpha = 120, 0.01
    nuisance = rng.normal(size=(n, 4))
    signature = rng.normal(size=(n, k)) + 0.5 * nuisance[:, :k]  # partly absorbed by the fit
    q_theta = statistics.basis(nuisance)
    sizes = statistics.minimum_detectable(signature, q_theta, alpha, power=0.8)
    assert sizes.shape == (k,) and np.all(np.isfinite(sizes)) and np.all(sizes > 0)

    def power(size, draws=2000):
        seen = 0
        for _ in range(draws):
            residual = signature[:, 0] * size + nuisance @ rng.normal(size=4) + rng.normal(size=n)
            seen += statistics.score_test(residual, q_theta, signature)["p_value"] < alpha
        return seen / draws

    assert abs(power(sizes[0]) - 0.8) < 0.04
    assert power(0.5 * sizes[0]) < 0.4
    # a signature the fitted parameters reproduce whole cannot be seen at any size
    assert np.all(np.isinf(statistics.minimum_detectable(nuisance[:, :k] @ np.eye(k), q_theta, alpha)))


def test_the_detectable_size_is_the_one_the_verdict_would_name():
    """A record's ``detectable`` is the size the verdict would name: never below the score test's
    (the BIC threshold can only raise it); with a model floor the change beyond the fitted
    parameters must reach min_effect x the floor where it acts, so at the reported size it does
    exactly that, and a larger floor asks proportionally more."""
    from BreastBiomechLib.discrepancy import statistics, verdicts
    from BreastBiomechLib.discrepancy.diagnosis import DiagnosisSettings, _detectable
    from BreastBiomechLib.discrepancy.observations import Observations

    rng = np.random.default_rng(11)
    n = 200
    sigma = np.full(n, 0.5)
    nuisance = rng.normal(size=(n, 3))
    signature = rng.normal(size=(n, 2)) * 0.3
    q_theta = statistics.basis(nuisance)

    def observed(floor):
        return Observations([f"f{i}" for i in range(n)], np.array(["landmarks"] * n), np.zeros(n), sigma,
                            np.zeros((n, 3)), floor_mm=0.0, measurement_sd=sigma, floor=np.full(n, floor))

    settings = DiagnosisSettings()
    score_only = statistics.minimum_detectable(signature, q_theta, 1e-3, power=0.8)
    quiet = _detectable(signature, q_theta, 1e-3, observed(1e-9), settings)
    assert np.all(np.array(quiet) >= score_only - 1e-12)
    loud = _detectable(signature, q_theta, 1e-3, observed(2.0), settings)
    beyond = statistics.project_off(signature, q_theta) * sigma[:, None]
    for j, size in enumerate(loud):
        assert size > quiet[j]
        assert verdicts.floor_ratio(beyond[:, j] * size, np.full(n, 2.0), settings.min_effect) == pytest.approx(1.0)
    louder = _detectable(signature, q_theta, 1e-3, observed(4.0), settings)
    np.testing.assert_allclose(louder, 2 * np.array(loud))
