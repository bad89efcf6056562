"""A cohort's unit of work: a :class:`Task` (a fit, a phantom case, a diagnosis) whose inputs and
result live on disk, and what became of it (:class:`TaskOutcome`).

A task's function is a module-level function (Dask ships it to a worker by reference) called as
``function(**kwargs, device=..., progress=...)``: ``device`` is the warp device it solves on in
that worker, ``progress(message)`` reports where it is (a short line; returning False asks it to
stop at the next chance, keeping what it has written) and its return value is a small JSON-able
summary. The function writes its result beside its inputs with :func:`~BreastBiomechLib.io.atomic.write_json_atomically`
(or renames a finished folder into place), so that a file that exists is complete: a rerun skips
the tasks whose results exist, and a worker lost mid-task costs that one task.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Task:
    """One unit of a cohort: ``key`` (unique and stable across runs, e.g. "fit/case1/iso-homo-cmaes"),
    the ``function`` and its ``kwargs`` (paths as strings, numbers, small dicts: they travel to
    the worker), the keys of the tasks it ``needs`` done first (keys not in the run are taken as
    done earlier), a ``label`` for progress lines (default: the key) and a ``priority``: of the
    tasks ready to run, a cluster starts those of higher priority first (give long tasks, and
    tasks that others need, a higher one, so a run does not end on one long task while the other
    workers idle); a run in one process keeps the given order."""

    key: str
    function: Callable
    kwargs: dict = field(default_factory=dict)
    needs: tuple[str, ...] = ()
    label: str = ""
    priority: int = 0

    @property
    def name(self) -> str:
        return self.label or self.key


@dataclass
class TaskOutcome:
    """What became of a task: ``ok`` with the function's ``result``, or its ``error`` ("Type:
    message") and where it was raised (``traceback``, for a log file); ``seconds`` of wall time in
    the worker (0 where it never started), the ``worker`` that ran it (its Dask name; "here" for
    a run in one process) and when it started (``started_at``, Unix time in s) — what a benchmark
    needs to say how busy each worker was (a task that raised on a cluster has neither: "", 0);
    ``earlier_errors``: the error and traceback of each earlier try that failed in a way worth
    trying again (:func:`~BreastBiomechLib.cohort.runner.transient_device_error`)."""

    key: str
    label: str
    ok: bool
    result: dict | None = None
    error: str = ""
    seconds: float = 0.0
    traceback: str = ""
    worker: str = ""
    started_at: float = 0.0
    earlier_errors: tuple[str, ...] = ()


def ordered(tasks: list[Task]) -> list[Task]:
    """``tasks`` in an order that runs each after the tasks it needs (stable otherwise). Refuses
    repeated keys and cycles, naming them."""
    keys = [t.key for t in tasks]
    repeated = sorted({k for k in keys if keys.count(k) > 1})
    if repeated:
        raise ValueError(f"task keys must be unique; repeated: {repeated}")
    by_key = {t.key: t for t in tasks}
    result: list[Task] = []
    state: dict[str, str] = {}

    def visit(task: Task, path: tuple[str, ...]) -> None:
        if state.get(task.key) == "done":
            return
        if state.get(task.key) == "visiting":
            raise ValueError("tasks need each other in a cycle: " + " -> ".join(path + (task.key,)))
        state[task.key] = "visiting"
        for need in task.needs:
            if need in by_key:
                visit(by_key[need], path + (task.key,))
        state[task.key] = "done"
        result.append(task)

    for task in tasks:
        visit(task, ())
    return result
