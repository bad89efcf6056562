"""Profile-likelihood intervals of an added effect's parameters.

The refit's linearised interval (estimate +- 1.96 sd from the Gauss-Newton information) is right
only where the features change linearly with the parameter. Friction does not: above the
coefficient at which the skin sticks to the plates nothing changes, so the residual is flat from
there to the top of the range, the linearised sd is that of the slope just below it, and an
estimate of 0.32 for a truth of 1.0 gets an interval that misses the truth by far
(docs/discrepancy.md, "Why friction refits below its truth"). A profile interval is the set of
values the data cannot tell from the estimate: each parameter is moved away from its estimate
and solved, the other parameters (the fit's and the added effects') re-fitted to the features at
each value by one linearised step from the refit's sensitivities, and the interval is where the
whitened residual sum of squares rises by less than the chi-square 95 % quantile of one degree of
freedom (3.84) above its least value; a saturating parameter's interval reaches the end of its
range ("open"), which says that the data bound it from one side only.

The model-error floor is taken in (issue 77): the deviance counts each feature's floor as
independent noise, but a model's discretisation and segmentation errors are systematic, alike
over hundreds of features, so a parameter whose predictions hardly change over a stretch of its
range (friction once the skin sticks) is pinned within that stretch by the model's own error: a
6 mm mesh of the truth's own labels misses the truth's landmarks by 1.1 mm at every mu from 0.3
to 1.5 while mu moves them by 0.01-0.04 mm there (docs/discrepancy.md). A value is therefore
also inside the interval where the features it predicts, the others re-fitted, differ from the
estimate's by less than the floor where they change (``tolerance`` times it:
:func:`~BreastBiomechLib.discrepancy.verdicts.floor_ratio`, the rule a named effect must pass):
no model with this error could tell it from the estimate. Each parameter keeps the interval of
the data alone (``data_interval``) beside it.

Each side of each parameter is walked in at most :data:`STEPS` first values (batched over the
parameters and sides): 2 linearised sd from the estimate (at least 2 % of the range), where the
data reject it the side is done; else the range's end, where they do not the side is open; else
four times as far as the first value (or halfway to the end) to bracket the bound, which is
interpolated between the last value inside and the first outside linearly in the root deviance
(linear in the parameter for a Gaussian likelihood). A well-determined parameter takes one solve
a side, a saturating one two on its open side. Where the first value outside lies far past the
threshold (:data:`ROOT_JUMP`), the bracket is halved until :data:`MAX_STEPS` values: the
features of a saturating parameter change little over a stretch and steeply past it, which one
line through the stretch brackets badly (a friction refitted to the top of its range, whose
first step down is the range's other end). Values whose solve fails are left out (counted in
``failed``). Where a launch has room for more models than the sides walking need (a GPU, or a
CPU with more worker processes than sides: :func:`room`), the values each side would try next
are solved beside them (:func:`walk`): the walk and its interval are the same, in fewer
launches."""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import lsq_linear

from BreastBiomechLib.discrepancy.observations import Observations
from BreastBiomechLib.discrepancy.state import ModelState
from BreastBiomechLib.discrepancy.variants import solve_variants
from BreastBiomechLib.discrepancy.verdicts import floor_ratio
from BreastBiomechLib.timing import staged

CHI2_95 = 3.841458820694124  # the chi-square 95 % quantile with one degree of freedom
STEPS = 3  # the first values of a side at most: the first step, the range's end, a value between
MAX_STEPS = 5  # solves per side at most, with the halvings of a bracket that jumps
ROOT_JUMP = 2.0  # a bracket whose outside value's root score (1: the threshold) is past this is halved
FIRST_STEP = (2.0, 0.02)  # the first value tried: this many linearised sd from the estimate, at least this share of the range
SECOND_STEP = 4.0  # the second this many times as far


@dataclass
class ProfiledParameter:
    """One parameter's profile: its ``key`` ("<effect>:<index>"), ``estimate``, the 95 %
    ``interval`` [low, high] (effect units; the values neither the data nor the model-error
    floor tell from the estimate), ``open`` [low, high] (True where the interval reaches that
    end of the parameter's range: nothing bounds it on that side), ``data_interval`` and
    ``data_open`` the same from the deviance alone, ``points`` [[value, deviance, floor ratio],
    ...] the values solved (the estimate at 0, 0; the floor ratio infinite where no floor was
    given) and ``failed`` the number of values whose solve failed."""

    key: str
    estimate: float
    interval: list[float]
    open: list[bool]
    data_interval: list[float] = field(default_factory=list)
    data_open: list[bool] = field(default_factory=list)
    points: list[list[float]] = field(default_factory=list)
    failed: int = 0

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class _Side:
    """One side of one parameter's walk: the parameter's ``index`` in its effect and ``column``
    in the design, the ``direction`` (-1 down, +1 up), the ``values`` to try first
    (:func:`side_values`' order), the parameter's ``estimate``, the values ``walked`` [(value,
    rss, floor ratio)], the ``failed`` solves and whether the side is ``done``. A value is
    rejected where the data reject it and its features differ from the estimate's by at least
    the floor (floor ratio >= 1). The first values end at the first rejected, or at the range's
    end not rejected (nothing between can be, for a profile that rises away from its least
    value: open), or after the third. Then, while the first value outside lies past
    :data:`ROOT_JUMP` times the threshold (a line between it and the last value inside would
    bracket the bound badly: a saturating parameter changes little over a stretch and steeply
    past it), the bracket is halved, up to :data:`MAX_STEPS` values in all."""

    index: int
    column: int
    direction: int
    values: list[float]
    estimate: float | None = None
    walked: list[tuple[float, float, float]] = field(default_factory=list)
    failed: int = 0
    done: bool = False
    _roots: list[float] = field(default_factory=list)  # each walked value's root score (1: the threshold)
    _first_over: bool = False  # the first values are done with

    @property
    def _tried(self) -> int:
        return len(self.walked) + self.failed

    def _bracket(self) -> tuple[float, float, float] | None:
        """Going outwards from the estimate: the last value inside, the first outside and its
        root score (None: none outside, or nothing inside before it)."""
        inside = self.estimate
        for (value, *_), root in sorted(zip(self.walked, self._roots), key=lambda w: w[0][0] * self.direction):
            if root > 1.0:
                return (inside, value, root) if inside is not None else None
            inside = value
        return None

    def _halving(self) -> bool:
        bracket = self._bracket()
        return self._tried < MAX_STEPS and bracket is not None and bracket[2] > ROOT_JUMP

    @property
    def pending(self) -> bool:
        if self.done:
            return False
        return self._tried < len(self.values) if not self._first_over else self._halving()

    @property
    def next_value(self) -> float:
        if not self._first_over:
            return self.values[self._tried]
        inside, outside, _ = self._bracket()
        return 0.5 * (inside + outside)

    def record(self, rss: float | None, rss_at_estimate: float, ratio: float = float("inf")) -> None:
        """The next value's profiled residual sum of squares (None: its solve failed) and its
        features' change from the estimate's against the model-error floor (``ratio``,
        :func:`~BreastBiomechLib.discrepancy.verdicts.floor_ratio`; infinite: no floor)."""
        tried = self._tried
        if rss is None:
            self.failed += 1
            if not self._first_over and self._tried >= len(self.values):
                self._first_over = True
            self.done = not self.pending
            return
        self.walked.append((self.next_value, rss, ratio))
        root = min(float(np.sqrt(max(rss - rss_at_estimate, 0.0) / CHI2_95)), ratio)
        self._roots.append(root)
        rejected = root > 1.0
        if not self._first_over:
            if len(self.values) == 1 or tried == 2:  # the end alone, or the bracketing value
                self._first_over = True
            elif tried == 0:  # the first step
                self._first_over = rejected
            elif not rejected:  # the range's end inside: open
                self.done = True
                return
        self.done = not self.pending


def side_values(estimate: float, sd: float, lower: float, upper: float, direction: int) -> list[float]:
    """The values a side is walked through (:data:`STEPS` at most) from ``estimate`` towards
    ``lower`` (``direction`` -1) or ``upper`` (+1), in the order they are tried: the first step,
    the range's end, then (tried only where the end is rejected) four times as far as the first
    step, or halfway to the end where that is not short of it; [the end] alone where the first
    step would reach it, [] where the estimate is at it."""
    end = upper if direction > 0 else lower
    span = upper - lower
    if abs(end - estimate) <= 1e-12 * max(span, 1.0):
        return []
    first = max(FIRST_STEP[0] * (sd if np.isfinite(sd) else 0.0), FIRST_STEP[1] * span)
    near = estimate + direction * first
    if (near - end) * direction >= 0.0:
        return [float(end)]
    inner = estimate + direction * SECOND_STEP * first
    if (inner - end) * direction >= 0.0:
        inner = 0.5 * (near + end)
    return [float(near), float(end), float(inner)]


def next_values(side: _Side, rss_at_estimate: float) -> list[float]:
    """The values ``side`` would try after its pending one, were that one inside (the walk goes
    on outwards) or far outside (past :data:`ROOT_JUMP`: the bracket is halved), in that order,
    each once; [] where neither would be tried."""
    out = []
    for rss in (rss_at_estimate, rss_at_estimate + CHI2_95 * (2.0 * ROOT_JUMP) ** 2):
        twin = copy.deepcopy(side)
        twin.record(rss, rss_at_estimate)
        if twin.pending and twin.next_value not in out and twin.next_value != side.next_value:
            out.append(twin.next_value)
    return out


def walk(sides: list[_Side], rss_at_estimate: float, solve: Callable[[list[tuple[_Side, float]]], list],
         room: int = 1) -> int:
    """Walk every side (:class:`_Side`) to its end: each launch ``solve([(side, value), ...])``
    (a result per pair: (rss, floor ratio), or None where the solve failed) holds the value each
    walking side needs, and, up to ``room`` models in all, the values those sides would try next
    (:func:`next_values`; those of the sides with the fewest values tried first); a value solved ahead is recorded when its
    side reaches it, unsolved by then. Returns the number of launches."""
    solved: dict[tuple[int, float], object] = {}
    launches = 0
    while any(side.pending for side in sides):
        active = [side for side in sides if side.pending]
        needed = [(side, side.next_value) for side in active if (id(side), side.next_value) not in solved]
        if needed:
            ahead = [(side, value) for side in active for value in next_values(side, rss_at_estimate)
                     if (id(side), value) not in solved]
            ahead.sort(key=lambda pair: len(pair[0].walked) + pair[0].failed)
            batch = needed + ahead[:max(room - len(needed), 0)]
            for (side, value), result in zip(batch, solve(batch)):
                solved[(id(side), value)] = result
            launches += 1
        for side in active:
            result = solved[(id(side), side.next_value)]
            if result is None:
                side.record(None, rss_at_estimate)
            else:
                side.record(result[0], rss_at_estimate, result[1])
    return launches


def room(device, walking: int) -> int:
    """How many models a launch of the profile's ``walking`` sides holds at about the cost of
    those alone: on a GPU twice as many (a batch's models share the launch), on a CPU its worker
    processes (:func:`~BreastBiomechLib.solver.cpu_pool.cpu_workers`), at least ``walking``."""
    import warp as wp

    from BreastBiomechLib.solver.cpu_pool import cpu_workers

    wp.init()
    if not wp.get_device(device).is_cpu:
        return 2 * walking
    return max(walking, cpu_workers(3 * walking))


def bound(estimate: float, walked: list[tuple], end: float) -> tuple[float, bool]:
    """One end of the interval from a side's walk ``walked`` [(value, deviance[, floor ratio]),
    ...] (any order) from ``estimate`` (deviance 0): going outwards, where the root deviance
    reaches sqrt(:data:`CHI2_95`) and, where a floor ratio is given, the ratio reaches 1 (the
    smaller of the two, each scaled to 1 at its threshold), interpolated linearly between the
    last value inside and the first outside; the range's ``end`` when no value is outside
    (open: True)."""
    inside_value, inside_root = estimate, 0.0
    for value, deviance, *ratio in sorted(walked, key=lambda point: abs(point[0] - estimate)):
        root = min([float(np.sqrt(max(deviance, 0.0) / CHI2_95)), *ratio])
        if root > 1.0:
            t = (1.0 - inside_root) / (root - inside_root)
            return float(inside_value + t * (value - inside_value)), False
        inside_value, inside_root = value, root
    return float(end), True


@staged("profile intervals")
def profile_intervals(state: ModelState, observations: Observations, effect_name: str, design: np.ndarray,
                      rss_at_estimate: float, progress: Callable[[str], None] | None = None,
                      residual_at_estimate: np.ndarray | None = None,
                      tolerance: float = 1.0) -> tuple[list[ProfiledParameter], np.ndarray | None]:
    """The profile intervals of the added effect ``effect_name``'s parameters at ``state`` (its
    refit), ``design`` (n, p) the features' change per unit of each of ``state.nuisance()``'s
    parameters (in that order; from the refit's last sensitivities) and ``rss_at_estimate`` the
    whitened residual sum of squares of ``state`` solved. With ``residual_at_estimate`` (n,) mm,
    that state's feature residual, a value whose features differ from the estimate's by less
    than ``tolerance`` times the model-error floor where they change is inside (see the module);
    without it the data alone decide. Returns the parameters' profiles and, where a value walked
    fitted the features better than the estimate (its profiled residual sum of squares lower:
    the refinement stopped short of the least), every parameter of ``state.nuisance()`` there
    (the others at their linearised re-fit) for the caller to solve and adopt; else None."""
    say = progress or (lambda message: None)
    effect, values = state.added[effect_name]
    nuisance = state.nuisance()
    keys = [key for key, *_ in nuisance]
    if design.shape != (len(observations.measured), len(keys)):
        raise ValueError(f"the profile's design has shape {design.shape}; it needs one row per feature and one "
                         f"column per parameter of the refit ({len(observations.measured)}, {len(keys)})")
    current = np.array([v for _, v, _, _ in nuisance])
    lower = np.array([lo for _, _, lo, _ in nuisance])
    upper = np.array([hi for _, _, _, hi in nuisance])
    weights = 1.0 / observations.sigma
    whitened_design = weights[:, None] * design
    sd = np.sqrt(np.maximum(np.diag(np.linalg.pinv(whitened_design.T @ whitened_design)), 0.0))

    if residual_at_estimate is not None and np.shape(residual_at_estimate) != (len(observations.measured),):
        raise ValueError(f"the residual at the estimate has shape {np.shape(residual_at_estimate)}; it needs one "
                         f"value per feature ({len(observations.measured)})")

    def profiled(column: int, value: float, displacement: np.ndarray) -> tuple[float, float, np.ndarray]:
        """The residual sum of squares at ``value`` solved, the other parameters re-fitted by one
        linearised step within their ranges, the features' change from the estimate's against
        the floor (infinite without ``residual_at_estimate``) and every parameter there."""
        others = [k for k in range(len(keys)) if k != column]
        whitened = weights * observations.residual(displacement)
        a = whitened_design[:, others]
        step = lsq_linear(a, whitened, bounds=(lower[others] - current[others], upper[others] - current[others])).x
        left = whitened - a @ step
        there = current.copy()
        there[others] += step
        there[column] = value
        if residual_at_estimate is None:
            return float(np.sum(left ** 2)), float("inf"), there
        change = np.asarray(residual_at_estimate, float) - observations.sigma * left
        return float(np.sum(left ** 2)), floor_ratio(change, observations.feature_floor, tolerance), there

    columns = [keys.index(f"{effect_name}:{j}") for j in range(len(effect.parameters))]
    sides = [_Side(j, columns[j], direction,
                   side_values(values[j], sd[columns[j]], parameter.lower, parameter.upper, direction), float(values[j]))
             for j, parameter in enumerate(effect.parameters) for direction in (-1, 1)]
    parameters_at = {}  # (side, value) solved -> every parameter there (the others re-fitted)

    def solve(batch: list[tuple[_Side, float]]) -> list:
        say(f"profile interval of {effect.title}: {len(batch)} solves")
        trials = []
        for side, value in batch:
            moved = values.copy()
            moved[side.index] = value
            trials.append(state.with_effect(effect, moved).variant())
        outcomes = solve_variants(trials, state.fitted.mesh.nodes, state.fitted.relaxation, state.fitted.device)
        results = []
        for (side, value), outcome in zip(batch, outcomes):
            if not outcome.ok:
                results.append(None)
                continue
            rss, ratio, parameters_at[(id(side), value)] = profiled(side.column, value, outcome.displacement)
            results.append((rss, ratio))
        return results

    walking = sum(side.pending for side in sides)
    walk(sides, rss_at_estimate, solve, room(state.fitted.device, walking) if walking else 1)
    better, least_walked = None, rss_at_estimate  # a value walked that fits better than the estimate
    for side in sides:
        for value, rss, _ in side.walked:
            if rss < least_walked:
                better, least_walked = parameters_at[(id(side), value)], rss
    least = min([rss_at_estimate] + [rss for side in sides for _, rss, _ in side.walked])
    out = []
    for j, parameter in enumerate(effect.parameters):
        low_side, high_side = (side for side in sides if side.index == j)
        estimate = float(values[j])
        ends, opened, data_ends, data_opened = [], [], [], []
        points = [[estimate, rss_at_estimate - least, 0.0]]
        for side, end in ((low_side, parameter.lower), (high_side, parameter.upper)):
            walked = [(value, rss - least, ratio) for value, rss, ratio in side.walked]
            points += [list(point) for point in walked]
            for limits, opens, kept in ((ends, opened, walked), (data_ends, data_opened, [w[:2] for w in walked])):
                limit, is_open = bound(estimate, kept, end)
                limits.append(limit)
                opens.append(is_open)
        out.append(ProfiledParameter(keys[low_side.column], estimate, ends, opened, data_ends, data_opened,
                                     sorted(points), low_side.failed + high_side.failed))
    return out, better
