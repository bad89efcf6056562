"""The profile interval's walk and bounds (discrepancy/profile.py) on deviance curves whose
intervals are known: a Gaussian likelihood (the interval is the linearised one), a parameter that
saturates (flat from a value to the top of its range: open above), and walks that stop early."""

from __future__ import annotations

import numpy as np
import pytest

from BreastBiomechLib.discrepancy.profile import STEPS, _Side, bound, side_values


def _walk(estimate, sd, lower, upper, direction, deviance):
    """A side walked as profile_intervals walks it (one value a step), on a known deviance."""
    side = _Side(0, 0, direction, side_values(estimate, sd, lower, upper, direction))
    while side.pending:
        side.record(deviance(side.next_value), 0.0)
    return side.walked


def test_a_gaussian_profile_gives_the_linearised_interval():
    estimate, sd = 0.6, 0.05
    deviance = lambda v: ((v - estimate) / sd) ** 2  # noqa: E731
    low = bound(estimate, _walk(estimate, sd, 0.0, 1.5, -1, deviance), 0.0)
    high = bound(estimate, _walk(estimate, sd, 0.0, 1.5, 1, deviance), 1.5)
    # root deviance is linear in the parameter: the interpolation is exact
    assert low == (pytest.approx(estimate - 1.959964 * sd, abs=1e-5), False)
    assert high == (pytest.approx(estimate + 1.959964 * sd, abs=1e-5), False)


def test_a_saturating_parameter_is_bounded_from_below_only():
    # friction: the residual falls steeply up to sticking at 0.25 and is flat above it
    estimate, sd = 0.32, 0.01  # the linearised sd of the slope below sticking: far too narrow
    deviance = lambda v: 0.0 if v >= 0.25 else (40.0 * (0.25 - v)) ** 2  # noqa: E731
    low, low_open = bound(estimate, _walk(estimate, sd, 0.0, 1.5, -1, deviance), 0.0)
    high, high_open = bound(estimate, _walk(estimate, sd, 0.0, 1.5, 1, deviance), 1.5)
    assert (high, high_open) == (1.5, True)  # the truth 1.0 is inside
    assert not low_open and 0.0 < low < 0.25
    assert estimate + 1.96 * sd < 1.0  # which the linearised interval would miss


def test_the_walk_tries_the_first_step_then_the_end_then_between():
    values = side_values(0.3, 0.01, 0.0, 1.5, 1)
    assert values == pytest.approx([0.33, 1.5, 0.42])  # 2 % of the range, the end, four times as far
    assert len(values) <= STEPS
    assert side_values(0.3, 0.01, 0.0, 1.5, -1) == pytest.approx([0.27, 0.0, 0.18])
    assert side_values(0.3, 0.1, 0.0, 1.5, -1) == pytest.approx([0.1, 0.0, 0.05])  # 4x past the end: halfway
    assert side_values(1.5, 0.01, 0.0, 1.5, 1) == []  # at the end: nothing to walk, the end is the bound
    assert side_values(1.45, 0.2, 0.0, 1.5, 1) == [1.5]  # the first step would leave the range
    assert side_values(0.0, float("nan"), -5.0, 5.0, 1) == pytest.approx([0.2, 5.0, 0.8])
    assert bound(1.5, [], 1.5) == (1.5, True)


def test_a_side_takes_only_the_solves_it_needs():
    # rejected at the first step: one solve; the end inside: two; the end rejected: three
    assert len(_walk(0.6, 0.05, 0.0, 1.5, 1, lambda v: ((v - 0.6) / 0.05) ** 2)) == 1
    assert len(_walk(0.32, 0.01, 0.0, 1.5, 1, lambda v: 0.0)) == 2
    walked = _walk(0.32, 0.01, 0.0, 1.5, -1, lambda v: 0.0 if v >= 0.25 else (40.0 * (0.25 - v)) ** 2)
    assert [v for v, _ in walked] == pytest.approx([0.29, 0.0, 0.2])


def test_a_value_outside_then_none_is_the_first_crossing():
    walked = [(0.7, 1.0), (1.0, 16.0)]  # root deviance 1 at 0.7, 4 at 1.0
    assert bound(0.5, walked, 1.5)[0] == pytest.approx(0.7 + (1.959964 - 1.0) / 3.0 * 0.3, abs=1e-5)
