"""The profile interval's walk and bounds (discrepancy/profile.py) on deviance curves whose
intervals are known: a Gaussian likelihood (the interval is the linearised one), a parameter that
saturates (flat from a value to the top of its range: open above), walks that stop early, and the
model-error floor: values whose features the floor cannot tell from the estimate's are inside."""

from __future__ import annotations

import numpy as np
import pytest

from BreastBiomechLib.discrepancy.profile import CHI2_95, STEPS, _Side, bound, next_values, side_values, walk
from BreastBiomechLib.discrepancy.verdicts import floor_ratio


def _walk(estimate, sd, lower, upper, direction, deviance, ratio=None):
    """A side walked as profile_intervals walks it (one value a step), on a known deviance and,
    where given, a known ratio of the features' change to the model-error floor."""
    side = _Side(0, 0, direction, side_values(estimate, sd, lower, upper, direction))
    while side.pending:
        value = side.next_value
        side.record(deviance(value), 0.0, *([ratio(value)] if ratio else []))
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
    assert [v for v, *_ in walked] == pytest.approx([0.29, 0.0, 0.2])


def test_a_value_outside_then_none_is_the_first_crossing():
    walked = [(0.7, 1.0), (1.0, 16.0)]  # root deviance 1 at 0.7, 4 at 1.0
    assert bound(0.5, walked, 1.5)[0] == pytest.approx(0.7 + (1.959964 - 1.0) / 3.0 * 0.3, abs=1e-5)


def test_values_the_model_floor_cannot_tell_from_the_estimate_are_inside():
    """The GPU demo's friction: refitted to 1.13 on a 4 mm mesh of the segmentation for a truth
    of 0.6, the data alone rejecting 1.05 (the deviance counts the floor as independent noise on
    hundreds of features), while from 0.3 up mu moves the features by a small part of the floor
    (a 6 mm mesh of the truth's labels: 0.01-0.04 mm against its 1.1 mm error)."""
    estimate, sd = 1.13, 0.02
    deviance = lambda v: (40.0 * (estimate - v)) ** 2 if v < estimate else 0.0  # noqa: E731
    ratio = lambda v: 0.05 if v >= 0.3 else 0.05 + 20.0 * (0.3 - v)  # noqa: E731  (1 at 0.2525)
    walked = _walk(estimate, sd, 0.0, 1.5, -1, deviance, ratio)
    data_low = bound(estimate, [w[:2] for w in walked], 0.0)
    low, low_open = bound(estimate, walked, 0.0)
    assert data_low[0] > 1.05 and not data_low[1]  # the data's own interval misses the truth
    assert not low_open and 0.0 < low <= 0.3 < 0.6  # with the floor: the truth is inside
    high = bound(estimate, _walk(estimate, sd, 0.0, 1.5, 1, deviance, ratio), 1.5)
    assert high == (1.5, True)


def test_a_floor_far_below_the_change_leaves_the_data_interval():
    estimate, sd = 0.6, 0.05
    deviance = lambda v: ((v - estimate) / sd) ** 2  # noqa: E731
    ratio = lambda v: 50.0 * abs(v - estimate) / sd  # noqa: E731  (1 at 0.02 sd: the data decide)
    for direction, end in ((-1, 0.0), (1, 1.5)):
        walked = _walk(estimate, sd, 0.0, 1.5, direction, deviance, ratio)
        assert len(walked) == 1  # rejected at the first step by both: no solve more than before
        assert bound(estimate, walked, end)[0] == pytest.approx(estimate + direction * 1.959964 * sd, abs=1e-5)


def test_the_walk_goes_on_where_the_floor_holds_a_value_the_data_reject():
    side = _Side(0, 0, -1, side_values(1.13, 0.02, 0.0, 1.5, -1))
    side.record(10 * CHI2_95, 0.0, 0.5)  # rejected by the data, inside the floor
    assert side.pending and not side.done
    side.record(10 * CHI2_95, 0.0, 3.0)  # the end: rejected by both
    assert side.pending  # the value between is tried
    side.record(CHI2_95 / 2, 0.0, 3.0)  # 0.97: inside by the data
    assert side.next_value == pytest.approx(0.485)  # the bracket (0.97, 0) halved
    side.record(10 * CHI2_95, 0.0, 0.2)
    assert side.next_value == pytest.approx(0.2425)
    side.record(10 * CHI2_95, 0.0, 1.5)
    assert not side.pending and side.done  # five values: MAX_STEPS
    assert bound(1.13, [(v, r, q) for v, r, q in side.walked], 0.0)[0] == pytest.approx(0.485 - 0.8 / 1.3 * 0.2425)
    # a bracket whose outside value is not far past the threshold ends the walk at the third value
    plain = _Side(0, 0, -1, side_values(1.13, 0.02, 0.0, 1.5, -1))
    for rss in (CHI2_95 / 2, 1.5 ** 2 * CHI2_95, CHI2_95 / 2):
        plain.record(rss, 0.0)
    assert plain.done and len(plain.walked) == STEPS


def test_an_estimate_at_the_top_of_its_range_is_bracketed_by_halving():
    """A friction refitted to the top of its range (1.5, a 8 mm mesh of the segmentation): its
    first step down is the range's other end, far outside; one line from there to the estimate
    put the bound at 1.01 where the features change little down to 0.3."""
    estimate = 1.5
    side = _Side(0, 0, -1, side_values(estimate, 10.0, 0.0, 1.5, -1), estimate)
    assert side.values == [0.0]
    ratio = lambda v: 0.05 if v >= 0.3 else 0.05 + 20.0 * (0.3 - v)  # noqa: E731  (1 at 0.2525)
    while side.pending:
        value = side.next_value
        side.record(158.0 * (1.0 - value / estimate) ** 2, 0.0, ratio(value))
    assert [v for v, *_ in side.walked] == pytest.approx([0.0, 0.75, 0.375, 0.1875, 0.28125])
    low, low_open = bound(estimate, side.walked, 0.0)
    assert not low_open and low == pytest.approx(0.2525, abs=0.01)


def test_the_floor_ratio_sizes_a_change_where_it_acts_against_the_floor_there():
    change = np.zeros(100)
    change[:10] = 1.0  # 1 mm on a tenth of the features
    floor = np.full(100, 0.25)
    floor[:10] = 0.5  # the floor is largest where it acts
    assert floor_ratio(change, floor) == pytest.approx(2.0)
    assert floor_ratio(change, floor, factor=2.0) == pytest.approx(1.0)
    assert floor_ratio(change, np.zeros(100)) == float("inf")
    assert floor_ratio(np.zeros(100), np.zeros(100)) == 0.0


def _sides(estimate, sd, lower, upper):
    return [_Side(0, 0, direction, side_values(estimate, sd, lower, upper, direction), estimate)
            for direction in (-1, 1)]


@pytest.mark.parametrize("estimate, deviance", [
    (0.32, lambda v: 0.0 if v >= 0.25 else (40.0 * (0.25 - v)) ** 2),  # saturating: flat above sticking
    (1.5, lambda v: 0.0 if v >= 0.25 else (40.0 * (0.25 - v)) ** 2),  # refitted to the top of its range
    (0.6, lambda v: ((v - 0.6) / 0.05) ** 2),  # Gaussian
    (1.13, lambda v: (40.0 * (1.13 - v)) ** 2 if v < 1.13 else 0.0),  # steep below, flat above
])
def test_values_solved_ahead_leave_the_walk_as_it_was_in_fewer_launches(estimate, deviance):
    """Where a launch has room, the values each side would try next are solved beside the ones
    it needs: every side walks the same values to the same interval, in no more launches (fewer
    where a side walks several values), and a value solved ahead that the walk never reaches is
    not recorded."""
    walks, launches, solved = {}, {}, {}
    for room in (1, 2, 4):
        sides, asked = _sides(estimate, 0.01, 0.0, 1.5), []

        def solve(batch, asked=asked):
            asked.extend(value for _, value in batch)
            return [(deviance(value), float("inf")) for _, value in batch]

        launches[room] = walk(sides, 0.0, solve, room)
        walks[room] = [side.walked for side in sides]
        solved[room] = asked
    assert walks[2] == walks[1] and walks[4] == walks[1]
    assert launches[4] <= launches[2] <= launches[1] == max(len(w) for w in walks[1])
    longest = max(len(w) for w in walks[1])
    if longest >= 2 and sum(len(w) > 0 for w in walks[1]) == 1:  # one side walking several values
        assert launches[2] < launches[1]
    recorded = {v for w in walks[4] for v, *_ in w}
    assert recorded <= set(solved[4]) and len(solved[4]) >= len(recorded)


def test_a_side_s_next_values_are_those_it_would_try_either_way():
    side = _Side(0, 0, -1, side_values(1.5, 0.01, 0.0, 1.5, -1), 1.5)  # the first step 1.47, the end 0, then 1.38
    assert side.next_value == pytest.approx(1.47)
    assert next_values(side, 0.0) == pytest.approx([0.0, 1.485])  # inside: the end; far outside: halved
    side.record(0.0, 0.0)  # 1.47 inside
    assert next_values(side, 0.0) == pytest.approx([1.38])  # the end inside: done; outside: between
    side.record(100.0, 0.0)  # the end far outside
    side.record(0.0, 0.0)  # 1.38 inside: the bracket (1.38, 0) is halved
    assert side.next_value == pytest.approx(0.69)
    assert next_values(side, 0.0) == pytest.approx([0.345, 1.035])
    side.record(0.0, 0.0)
    assert next_values(side, 0.0) == []  # the fifth value is the last
