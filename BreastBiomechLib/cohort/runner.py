"""Run a cohort's tasks where :func:`~BreastBiomechLib.cohort.cluster.place` says: submit them
(each once the tasks it needs have finished; of the tasks ready, those of higher priority
first), follow their progress, report each outcome as it comes, and cancel cleanly.

- A task that raises is reported with its error; the others go on (those that need it are
  reported as not run).
- A worker lost mid-task (killed, out of memory) costs that task: Dask runs it again on another
  worker, where it resumes from what it wrote (fits replay their evaluations file); a task whose
  workers keep dying is reported after Dask's allowed failures (3 by default).
- A task that fails with a CUDA graph capture error (:func:`transient_device_error`) is run once
  more (resuming from what it wrote); the outcome keeps the first try's error.
- Cancel (the progress callback returns False, or Ctrl-C): running tasks are asked to stop at
  their next progress report (a fit after its batch, keeping every evaluation), tasks not
  started are dropped, and :class:`CohortCancelled` is raised; a rerun resumes.
- Progress: workers send each task's progress lines to the client as Dask events (at most one
  a second per task), so the command line and the Slicer module show what every worker does.
"""

from __future__ import annotations

import time
import traceback
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field

from BreastBiomechLib.cohort.cluster import Placement, cohort_client, dashboard_link
from BreastBiomechLib.cohort.tasks import Task, TaskOutcome, ordered

PROGRESS_TOPIC = "breastbiomech-progress"
REPORT_EVERY_S = 1.0  # a task's progress lines reach the client at most this often
# CUDA's words for a graph capture that an operation broke (errors 900, 901 and 906). The varied
# discrepancy suite lost 4 of 20 cases to them on 2026-12-07 (one H100, five workers sharing it),
# each at the first launch of a capture, and all four ran through when run again: a failure of
# one try, not of the task. Its likely cause, a warp object freed in another thread of the
# worker, is removed for local clusters (cluster.WORKER_CONFIG); a user's cluster may still have it.
TRANSIENT_DEVICE_ERRORS = ("error during capture", "when stream is capturing", "depend on a capturing")
RETRIES_AFTER_A_TRANSIENT_DEVICE_ERROR = 1


def transient_device_error(error: str) -> bool:
    """Whether a task's ``error`` ("Type: message") is a CUDA graph capture failure, which the
    task is run again after (:data:`TRANSIENT_DEVICE_ERRORS`)."""
    return any(words in error for words in TRANSIENT_DEVICE_ERRORS)


def _runs_again(error: str, earlier) -> bool:
    """Whether a task that failed with ``error`` after the ``earlier`` failed tries is run once more."""
    return transient_device_error(error) and len(earlier) < RETRIES_AFTER_A_TRANSIENT_DEVICE_ERROR


class CohortCancelled(Exception):
    """The run was cancelled; what finished is on disk and a rerun resumes."""


@dataclass
class CohortProgress:
    """Where a run stands: ``total`` tasks, how many ``finished`` and ``failed``, the latest
    progress line of each ``running`` task (by label), where the run goes (``where``) and the
    cluster's ``dashboard`` link (None: none)."""

    total: int
    where: str
    finished: int = 0
    failed: int = 0
    running: dict[str, str] = field(default_factory=dict)
    dashboard: str | None = None

    @property
    def done(self) -> int:
        return self.finished + self.failed

    def line(self, width: int = 24) -> str:
        """One line for a terminal: a bar over the tasks, the counts and the running tasks."""
        filled = int(width * self.done / max(self.total, 1))
        text = f"[{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total} tasks"
        if self.failed:
            text += f", {self.failed} failed"
        if self.running:
            text += "; " + "; ".join(f"{label}: {message}" for label, message in sorted(self.running.items()))
        return text


def run_tasks(tasks: list[Task], placement: Placement,
              progress: Callable[[CohortProgress], bool | None] | None = None,
              on_outcome: Callable[[TaskOutcome], None] | None = None,
              dashboard: str | None = ":8787", poll_s: float = 0.25) -> list[TaskOutcome]:
    """Run ``tasks`` at ``placement``; returns their outcomes in the order they ended.
    ``progress(state)`` is called as things change (returning False cancels); ``on_outcome(o)``
    as each task ends (in this process and thread, e.g. to rewrite a summary file)."""
    tasks = ordered(list(tasks))
    state = CohortProgress(len(tasks), placement.describe())
    if not tasks:
        return []
    if placement.workers == 0 and not placement.scheduler:
        return _run_here(tasks, placement.task_device, state, progress, on_outcome)
    with cohort_client(placement, dashboard) as client:
        return _run_on(client, tasks, placement.task_device, state, progress, on_outcome, poll_s)


def _record(outcome: TaskOutcome, state: CohortProgress, outcomes: list, on_outcome) -> None:
    state.running.pop(outcome.label, None)
    if outcome.ok:
        state.finished += 1
    else:
        state.failed += 1
    outcomes.append(outcome)
    if on_outcome is not None:
        on_outcome(outcome)


def _run_here(tasks, device, state, progress, on_outcome) -> list[TaskOutcome]:
    """Every task in this process, one after another."""
    outcomes: list[TaskOutcome] = []
    failed: set[str] = set()
    cancelled = [False]
    for task in tasks:
        missing = [k for k in task.needs if k in failed]
        if missing:
            failed.add(task.key)
            _record(TaskOutcome(task.key, task.name, False, error=f"not run: it needs {', '.join(missing)}, which "
                                "failed"), state, outcomes, on_outcome)
        else:
            def report(message, label=task.name):
                state.running[label] = message
                if progress is not None and progress(state) is False:
                    cancelled[0] = True
                return not cancelled[0]

            earlier: list[str] = []
            while True:
                report("started")
                started, started_at = time.perf_counter(), time.time()
                try:
                    result = task.function(**task.kwargs, device=device, progress=report)
                except Exception as error:  # noqa: BLE001 - reported, and the run goes on
                    text = f"{type(error).__name__}: {error}"
                    if _runs_again(text, earlier):
                        earlier.append(f"{text}\n{traceback.format_exc()}")
                        continue
                    failed.add(task.key)
                    _record(TaskOutcome(task.key, task.name, False, error=text, seconds=time.perf_counter() - started,
                                        traceback=traceback.format_exc(), worker="here", started_at=started_at,
                                        earlier_errors=tuple(earlier)), state, outcomes, on_outcome)
                else:
                    _record(TaskOutcome(task.key, task.name, True, result, seconds=time.perf_counter() - started,
                                        worker="here", started_at=started_at, earlier_errors=tuple(earlier)),
                            state, outcomes, on_outcome)
                break
        if progress is not None and progress(state) is False:
            cancelled[0] = True
        if cancelled[0]:
            raise CohortCancelled(f"cancelled after {state.done} of {state.total} tasks; rerun to resume")
    return outcomes


def _execute(label: str, function, kwargs: dict, device, cancel_name: str) -> dict:
    """In a worker: run one task, sending its progress lines as events and stopping it when the
    run's cancel event is set."""
    from distributed import Event, get_worker

    worker = get_worker()
    cancel = Event(cancel_name)
    last = [-REPORT_EVERY_S]
    stop = [False]

    def report(message: str) -> bool:
        now = time.monotonic()
        if now - last[0] >= REPORT_EVERY_S:
            last[0] = now
            worker.log_event(PROGRESS_TOPIC, {"run": cancel_name, "label": label, "message": message})
            stop[0] = stop[0] or cancel.is_set()
        return not stop[0]

    report("started")
    started, started_at = time.perf_counter(), time.time()
    result = function(**kwargs, device=device, progress=report)
    worker.log_event(PROGRESS_TOPIC, {"run": cancel_name, "label": label, "message": None})
    return {"result": result, "seconds": time.perf_counter() - started, "worker": str(worker.name),
            "started_at": started_at}


def _failure(error: BaseException) -> str:
    from distributed import KilledWorker

    if isinstance(error, KilledWorker):
        return ("KilledWorker: the workers running it died each time (killed, or out of memory: see the worker logs "
                "or the dashboard); rerun to try again")
    return f"{type(error).__name__}: {error}"


def _run_on(client, tasks, device, state, progress, on_outcome, poll_s) -> list[TaskOutcome]:
    """Submit each task to ``client``'s cluster once the tasks it needs have finished, and follow
    them to the end (or the cancel). Tasks reach Dask without dependencies between them (their
    inputs are on disk), so a ready task goes to whichever worker is free — given as Dask
    dependencies, a case's fits would all queue on the worker that made its mesh."""
    from distributed import Event, as_completed

    state.dashboard = dashboard_link(client)
    token = uuid.uuid4().hex[:8]  # keys of this run, apart from any other run on a shared scheduler
    cancel = Event(f"breastbiomech-cancel-{token}", client=client)
    in_run = {task.key for task in tasks}
    waiting = list(tasks)  # in an order that puts each task after those it needs
    succeeded: dict[str, bool] = {}
    earlier: dict[str, list[str]] = {}  # per task, the errors of its tries run again
    by_future, futures = {}, []
    finished = as_completed()
    outcomes: list[TaskOutcome] = []

    def on_event(event) -> None:
        _, message = event
        if message.get("run") != cancel.name:  # another run's task on a shared scheduler
            return
        if message["message"] is None:
            state.running.pop(message["label"], None)
        else:
            state.running[message["label"]] = message["message"]

    def submit_ready() -> None:
        ready = []
        for task in list(waiting):
            needs = [k for k in task.needs if k in in_run]
            missing = [k for k in needs if succeeded.get(k) is False]
            if missing:
                waiting.remove(task)
                succeeded[task.key] = False
                _record(TaskOutcome(task.key, task.name, False, error=f"not run: it needs {', '.join(missing)}, "
                                                                      "which failed"), state, outcomes, on_outcome)
            elif all(succeeded.get(k) for k in needs):
                waiting.remove(task)
                ready.append(task)
        for task in sorted(ready, key=lambda t: -t.priority):  # a free worker takes the first to arrive
            submit(task)

    def submit(task) -> None:
        tries = len(earlier.get(task.key, ()))
        future = client.submit(_execute, task.name, task.function, task.kwargs, device, cancel.name,
                               key=f"{task.key}@{token}" + (f"#{tries + 1}" if tries else ""), pure=False,
                               priority=task.priority)
        by_future[future.key] = task
        futures.append(future)
        finished.add(future)

    client.subscribe_topic(PROGRESS_TOPIC, on_event)
    try:
        while state.done < state.total:
            submit_ready()
            for future in finished.next_batch(block=False):
                task = by_future[future.key]
                if future.status not in ("finished", "error"):  # lost with its worker: Dask runs it again
                    finished.add(future)
                    continue
                tried = tuple(earlier.get(task.key, ()))
                if future.status == "finished":
                    value = future.result()
                    outcome = TaskOutcome(task.key, task.name, True, value["result"], seconds=value["seconds"],
                                          worker=value["worker"], started_at=value["started_at"],
                                          earlier_errors=tried)
                else:
                    error, where = _failure(future.exception()), "".join(traceback.format_tb(future.traceback()))
                    if _runs_again(error, tried):
                        earlier.setdefault(task.key, []).append(f"{error}\n{where}")
                        submit(task)
                        continue
                    outcome = TaskOutcome(task.key, task.name, False, error=error, traceback=where,
                                          earlier_errors=tried)
                succeeded[task.key] = outcome.ok
                _record(outcome, state, outcomes, on_outcome)
            if progress is not None and progress(state) is False:
                raise CohortCancelled(f"cancelled after {state.done} of {state.total} tasks; rerun to resume")
            if state.done < state.total:
                time.sleep(poll_s)
    except (CohortCancelled, KeyboardInterrupt):
        cancel.set()  # running tasks stop at their next progress report, keeping what they wrote
        client.cancel(futures)  # tasks not yet submitted are dropped
        raise
    finally:
        client.unsubscribe_topic(PROGRESS_TOPIC)
    return outcomes
