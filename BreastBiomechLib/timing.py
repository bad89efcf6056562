"""Wall time per stage of a run, for the benchmarks that say where a user waits (issue 81).

A :class:`StageClock` made current with :func:`clocked` collects the seconds spent inside each
:func:`stage` opened while it is current, in this thread or the code it calls, however deep:
``with stage("solving"): ...`` in the solver, ``with stage("registration"): ...`` in the
diagnosis, and so on. Stages nest; each stage's *own* seconds exclude the stages opened inside
it, so the own seconds of all stages and the clock's ``unstaged`` remainder add up to the wall
time. Without a current clock a stage costs one context-variable read, so library code marks
its stages unconditionally.

Seconds are wall-clock (``time.perf_counter``). A GPU runs its kernels after the launch returns;
a clock with ``synchronise`` set (e.g. ``warp.synchronize``) waits for the device on entering and
leaving every stage, so each stage holds its own kernels' time (at the cost of those waits).
Without it a stage that only launches counts little and the one that reads the results back
counts the rest."""

from __future__ import annotations

import contextvars
import functools
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field

_CURRENT: contextvars.ContextVar["StageClock | None"] = contextvars.ContextVar("breastbiomech_stage_clock",
                                                                             default=None)


@dataclass
class StageTotal:
    """One stage's totals: ``own_s`` its seconds less the stages inside it, ``total_s`` with
    them, ``count`` how many times it was entered."""

    own_s: float = 0.0
    total_s: float = 0.0
    count: int = 0


@dataclass
class StageClock:
    """Seconds per stage name while current (:func:`clocked`). ``synchronise``: called on
    entering and leaving every stage (see the module notes); ``now``: the time in seconds
    (``time.perf_counter``); ``started`` and ``stopped`` its readings when the clock was made and
    when :func:`clocked` ended (None while it runs)."""

    synchronise: Callable[[], object] | None = None
    now: Callable[[], float] = time.perf_counter
    stages: dict[str, StageTotal] = field(default_factory=dict)
    started: float | None = None
    stopped: float | None = None
    _open: list[list] = field(default_factory=list)  # [name, entered, seconds of the stages inside]

    def __post_init__(self) -> None:
        if self.started is None:
            self.started = self.now()

    @property
    def wall_s(self) -> float:
        """Seconds from the clock's making to its stop (to now while it runs)."""
        return (self.stopped if self.stopped is not None else self.now()) - self.started

    @property
    def unstaged_s(self) -> float:
        """Wall seconds inside no stage (imports, reading and writing files not marked, Python)."""
        return self.wall_s - sum(s.own_s for s in self.stages.values())

    def share(self, name: str) -> float:
        """Fraction of the wall time spent in stage ``name`` itself (0 when never entered)."""
        wall = self.wall_s
        return self.stages[name].own_s / wall if name in self.stages and wall > 0 else 0.0

    def to_dict(self) -> dict:
        """{"wall_s", "unstaged_s", "stages": {name: {"own_s", "total_s", "count", "share"}}},
        stages by own seconds, largest first; seconds rounded to ms."""
        wall = self.wall_s
        ordered = sorted(self.stages.items(), key=lambda item: -item[1].own_s)
        return {"wall_s": round(wall, 3), "unstaged_s": round(self.unstaged_s, 3),
                "stages": {name: {"own_s": round(s.own_s, 3), "total_s": round(s.total_s, 3), "count": s.count,
                                  "share": round(s.own_s / wall, 4) if wall > 0 else 0.0}
                           for name, s in ordered}}

    def table(self) -> str:
        """The stages as a Markdown table: stage, times entered, own seconds, share of the wall
        time, seconds with the stages inside it."""
        data = self.to_dict()
        wall = data["wall_s"]
        rows = [f"| {name} | {s['count']} | {s['own_s']:.1f} | {s['share']:.0%} | {s['total_s']:.1f} |"
                for name, s in data["stages"].items()]
        rows.append(f"| (outside the stages: file reading and writing, Python) | | {data['unstaged_s']:.1f} | "
                    f"{data['unstaged_s'] / wall if wall > 0 else 0:.0%} | |")
        return "\n".join(["| stage | times | seconds | share | seconds with the stages inside |",
                          "|---|---|---|---|---|", *rows, f"| **wall** | | **{wall:.1f}** | 100% | |"])

    def _enter(self, name: str) -> None:
        if self.synchronise is not None:
            self.synchronise()
        self._open.append([name, self.now(), 0.0])

    def _leave(self) -> None:
        if self.synchronise is not None:
            self.synchronise()
        name, entered, inside = self._open.pop()
        total = self.now() - entered
        entry = self.stages.setdefault(name, StageTotal())
        entry.own_s += total - inside
        entry.count += 1
        if not any(frame[0] == name for frame in self._open):  # a stage re-entered inside itself counts once
            entry.total_s += total
        if self._open:
            self._open[-1][2] += total


@contextmanager
def clocked(clock: StageClock | None = None):
    """Make ``clock`` (default a new one) current for the ``with`` block; yields it, stopped at
    the block's end. Clocks nest: the outer one resumes after the block, and does not see the
    inner one's stages."""
    clock = clock if clock is not None else StageClock()
    token = _CURRENT.set(clock)
    try:
        yield clock
    finally:
        clock.stopped = clock.now()
        _CURRENT.reset(token)


@contextmanager
def stage(name: str):
    """Count the ``with`` block's wall seconds to stage ``name`` of the current clock, if any."""
    clock = _CURRENT.get()
    if clock is None:
        yield
        return
    clock._enter(name)
    try:
        yield
    finally:
        clock._leave()


def staged(name: str):
    """Decorator: every call of the function counts to stage ``name`` (:func:`stage`)."""
    def decorate(function):
        @functools.wraps(function)
        def timed(*args, **kwargs):
            with stage(name):
                return function(*args, **kwargs)
        return timed
    return decorate


def current_clock() -> StageClock | None:
    """The clock made current by the innermost :func:`clocked`, or None."""
    return _CURRENT.get()
