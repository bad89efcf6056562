"""The profile interval's walk and bounds (discrepancy/profile.py) on deviance curves whose
intervals are known: a Gaussian likelihood (the interval is the linearised one), a parameter that
saturates (flat from a value to the top of its range: open above), and walks that stop early."""

from __future__ import annotations

import numpy as np
import pytest

from BreastBiomechLib.discrepancy.profile import CHI2_95, STEPS, bound, side_values


def _walk(estimate, sd, lower, upper, direction, deviance):
    """A side walked as profile_intervals walks it: values in turn until one is rejected."""
    walked = []
    for value in side_values(estimate, sd, lower, upper, direction):
        walked.append((value, deviance(value)))
        if walked[-1][1] > CHI2_95:
            break
    return walked


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


def test_the_walk_goes_outwards_within_the_range_and_ends_at_its_end():
    values = side_values(0.3, 0.01, 0.0, 1.5, 1)
    assert values == pytest.approx([0.33, 0.42, 1.5])  # 2 % of the range, four times as far, the end
    assert len(values) <= STEPS and np.all(np.diff(values) > 0)
    assert side_values(0.3, 0.01, 0.0, 1.5, -1) == pytest.approx([0.27, 0.18, 0.0])
    assert side_values(1.5, 0.01, 0.0, 1.5, 1) == []  # at the end: nothing to walk, the end is the bound
    assert side_values(1.45, 0.2, 0.0, 1.5, 1) == [1.5]  # the first step would leave the range
    assert side_values(0.0, float("nan"), -5.0, 5.0, 1) == pytest.approx([0.2, 0.8, 5.0])
    assert bound(1.5, [], 1.5) == (1.5, True)


def test_a_value_outside_then_none_is_the_first_crossing():
    walked = [(0.7, 1.0), (1.0, 16.0)]  # root deviance 1 at 0.7, 4 at 1.0
    assert bound(0.5, walked, 1.5)[0] == pytest.approx(0.7 + (1.959964 - 1.0) / 3.0 * 0.3, abs=1e-5)
