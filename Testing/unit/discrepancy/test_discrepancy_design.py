"""The design of the next measurement's separations (discrepancy/design.py) on whitened rows made
by hand: an effect's separation is its signature beyond the fitted parameters and its rival,
stacking a state never lowers it, states are stacked parameter by parameter, and the closest
rival is the most nearly parallel candidate. The whole design on a fitted case:
Testing/integration/test_discrepancy.py."""

from __future__ import annotations

import numpy as np
import pytest

from BreastBiomechLib.discrepancy.design import Rows, residual_norm


def _rows(rng, n=40):
    stiffer = rng.standard_normal(n)  # a fitted parameter's signature
    hold = 0.9 * stiffer + 0.1 * rng.standard_normal(n)  # mostly taken up by it
    tilt = rng.standard_normal(n)
    twin = tilt + 0.05 * rng.standard_normal(n)  # nearly parallel to tilt
    return Rows({"muscle.E": stiffer}, {"chest-wall": hold, "plate-tilt": tilt, "plate-offset": twin}, n=n)


def test_a_separation_is_the_signature_beyond_the_fitted_parameters_and_the_rival():
    rng = np.random.default_rng(3)
    rows = _rows(rng)
    stiffer, hold = rows.nuisance["muscle.E"], rows.effects["chest-wall"]
    beyond = hold - stiffer * (stiffer @ hold) / (stiffer @ stiffer)
    assert rows.separation("chest-wall", None) == pytest.approx(np.linalg.norm(beyond))
    assert rows.separation("chest-wall", None) < 0.2 * np.linalg.norm(hold)  # absorbed
    # an effect in the span of the fitted parameters cannot be told apart; one the rival spans neither
    assert residual_norm(2.0 * stiffer, rows.fitted_span()) == pytest.approx(0.0, abs=1e-9)
    assert rows.separation("plate-offset", "plate-tilt") < 0.1 * rows.separation("plate-offset", None)
    assert rows.closest_rival("plate-offset") == "plate-tilt" and rows.closest_rival("plate-tilt") == "plate-offset"
    assert residual_norm(hold, np.zeros((len(hold), 0))) == pytest.approx(np.linalg.norm(hold))


def test_a_further_state_never_lowers_a_separation_and_is_stacked_parameter_by_parameter():
    rng = np.random.default_rng(4)
    now, further = _rows(rng), _rows(rng, n=25)
    further.nuisance = {"muscle.E": further.nuisance["muscle.E"], "glandular.E": rng.standard_normal(25)}
    del further.effects["plate-offset"]
    further.skipped = {"plate-offset": "not available"}
    stacked = now.stacked(further)
    assert stacked.n == 65 and list(stacked.nuisance) == ["muscle.E", "glandular.E"]
    np.testing.assert_array_equal(stacked.nuisance["glandular.E"][:40], 0.0)  # the first state lacks it
    assert set(stacked.effects) == {"chest-wall", "plate-tilt"} and stacked.skipped == {"plate-offset": "not available"}
    for effect, rival in (("chest-wall", "plate-tilt"), ("chest-wall", None), ("plate-tilt", "chest-wall")):
        assert stacked.separation(effect, rival) >= now.separation(effect, rival) - 1e-12
    # a state in which the hold moves the features against the stiffer muscle separates them
    further.effects["chest-wall"] = -0.9 * further.nuisance["muscle.E"]
    stacked = now.stacked(further)
    assert stacked.separation("chest-wall", None) > 3 * now.separation("chest-wall", None)
