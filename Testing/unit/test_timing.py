"""The stage clock (BreastBiomechLib.timing): own seconds of nested stages, counts, the unstaged
remainder, nesting of clocks, the device synchronisation hook; driven by a counter so every
figure is exact."""

from __future__ import annotations

import threading

import pytest

from BreastBiomechLib.timing import StageClock, clocked, current_clock, stage, staged


class Ticks:
    """A clock that moves only when told: ``advance(s)`` seconds."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t

    def advance(self, seconds: float) -> None:
        self.t += seconds


def test_nested_stages_count_their_own_seconds_and_add_up_to_the_wall_time():
    ticks = Ticks()
    with clocked(StageClock(now=ticks)) as clock:
        ticks.advance(1.0)  # outside every stage
        with stage("fit"):
            ticks.advance(2.0)
            with stage("solving"):
                ticks.advance(5.0)
            ticks.advance(0.5)
            with stage("solving"):
                ticks.advance(3.0)
        with stage("solving"):
            ticks.advance(4.0)
    figures = clock.to_dict()
    assert figures["wall_s"] == pytest.approx(15.5)
    assert figures["stages"]["solving"] == {"own_s": 12.0, "total_s": 12.0, "count": 3, "share": round(12 / 15.5, 4)}
    assert figures["stages"]["fit"]["own_s"] == pytest.approx(2.5)
    assert figures["stages"]["fit"]["total_s"] == pytest.approx(10.5)
    assert figures["unstaged_s"] == pytest.approx(1.0)
    assert list(figures["stages"]) == ["solving", "fit"]  # largest own seconds first
    assert clock.share("solving") == pytest.approx(12 / 15.5)
    assert clock.share("never entered") == 0.0
    assert "| solving | 3 | 12.0 | 77% | 12.0 |" in clock.table() and "| fit | 1 | 2.5 | 16% | 10.5 |" in clock.table()


def test_a_stage_entered_inside_itself_counts_its_span_once():
    ticks = Ticks()
    with clocked(StageClock(now=ticks)) as clock:
        with stage("solving"):  # a batch split into launches that solve_batch makes itself
            ticks.advance(1.0)
            with stage("solving"):
                ticks.advance(2.0)
    solving = clock.stages["solving"]
    assert (solving.own_s, solving.total_s, solving.count) == (3.0, 3.0, 2)


def test_a_stage_raising_is_still_counted_and_leaves_the_clock_consistent():
    ticks = Ticks()
    with clocked(StageClock(now=ticks)) as clock:
        with pytest.raises(RuntimeError):
            with stage("meshing"):
                ticks.advance(2.0)
                raise RuntimeError("TetGen failed")
        with stage("solving"):
            ticks.advance(1.0)
    assert clock.stages["meshing"].own_s == 2.0 and clock.stages["solving"].own_s == 1.0
    assert clock.unstaged_s == pytest.approx(0.0)


def test_without_a_clock_stages_do_nothing_and_the_decorator_returns_the_value():
    @staged("pictures")
    def draw(x, scale=2):
        """Docstring kept."""
        return x * scale

    assert current_clock() is None
    with stage("solving"):
        pass
    assert draw(3, scale=4) == 12 and draw.__doc__ == "Docstring kept."
    ticks = Ticks()
    with clocked(StageClock(now=ticks)) as clock:
        draw(1)
        draw(2)
    assert clock.stages["pictures"].count == 2


def test_clocks_nest_and_the_outer_one_resumes_without_the_inner_stages():
    ticks = Ticks()
    with clocked(StageClock(now=ticks)) as outer:
        with stage("fit"):
            ticks.advance(1.0)
            with clocked(StageClock(now=ticks)) as inner:
                with stage("solving"):
                    ticks.advance(2.0)
            assert current_clock() is outer
    assert "solving" not in outer.stages and outer.stages["fit"].own_s == 3.0
    assert inner.stages["solving"].own_s == 2.0 and inner.wall_s == 2.0
    assert current_clock() is None


def test_the_synchronise_hook_runs_on_entering_and_leaving_every_stage():
    calls = []
    with clocked(StageClock(synchronise=lambda: calls.append(1))):
        with stage("solving"):
            with stage("image warping"):
                pass
    assert len(calls) == 4


def test_a_thread_started_inside_a_clock_does_not_write_into_it():
    """Each thread sees its own context: a worker thread's stages never corrupt the nesting of
    the thread that opened the clock."""
    ticks = Ticks()
    seen = []
    with clocked(StageClock(now=ticks)) as clock:
        worker = threading.Thread(target=lambda: seen.append(current_clock()))
        worker.start()
        worker.join()
    assert seen == [None] and clock.stages == {}
