"""Bookkeeping of an optimisation: every evaluation appended to a JSON-lines results file as it
is made, the evaluation budget (count and wall time), progress and cancel, and resume.

Resume replays: the optimisers are deterministic for a given seed, so a rerun with the same
settings asks for the same positions in the same order, and those already in the results file
are answered from it without a solve. A position asked for again within a run is answered from
its first evaluation too (it counts against the budget, and is not written twice), so a resumed
run solves exactly the batches an uninterrupted one does. An interruption loses at most the batch
in flight (a record cut short by a kill mid-write is dropped on resume).
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from BreastBiomechLib.errors import InputError, one_line
from BreastBiomechLib.io.atomic import write_text_atomically
from BreastBiomechLib.optimisation.forward import Evaluation


def read_evaluations(path: str | Path) -> list[Evaluation]:
    """Every evaluation recorded in a results file (JSON lines). A last line without its newline
    (a run killed mid-write) is left out; any other line that is not a whole evaluation record
    raises :class:`~BreastBiomechLib.errors.InputError` naming the file and the line."""
    path = Path(path)
    evaluations = []
    for number, line in enumerate(path.read_text().splitlines(keepends=True), 1):
        if not line.endswith("\n"):
            break
        if not line.strip():
            continue
        try:
            record = json.loads(line)
            record.pop("index", None)
            record.pop("phase", None)
            evaluation = Evaluation(**record)
            z = np.asarray(evaluation.z, dtype=np.float64)
            if z.ndim != 1 or not np.isfinite(z).all() or not isinstance(evaluation.values, dict):
                raise ValueError("its position z is not a list of finite numbers")
            if isinstance(evaluation.objective, bool) or not isinstance(evaluation.objective, (int, float)):
                raise ValueError(f"its objective is {evaluation.objective!r}, not a number")
        except (ValueError, TypeError, AttributeError) as error:
            raise InputError(f"{path}: line {number} is not an evaluation record ({one_line(error)}); the file was "
                             "changed by something other than the fit: move it away and fit again") from None
        evaluations.append(evaluation)
    return evaluations


class BudgetExhausted(Exception):
    """Raised inside an optimiser when the evaluation or time budget is spent, or on cancel."""


class EvaluationLog:
    """Counts, caches and records evaluations for the optimisers.

    ``evaluate``: unit positions (B, d) -> list of :class:`Evaluation` (one batched solve);
    ``budget``: most evaluations in all (replayed ones included, so that a resumed run ends where
    an uninterrupted one would); ``seconds``: most wall time of this run (None: no limit);
    ``path``: the results file (JSON lines; None: kept in memory only), whose evaluations are
    replayed when ``resume``; ``progress(done, budget, best objective, message)``: called after
    every batch, returning False cancels."""

    def __init__(self, evaluate: Callable[[np.ndarray], list[Evaluation]], budget: int,
                 seconds: float | None = None, path: str | Path | None = None, resume: bool = False,
                 progress: Callable[[int, int, float, str], bool | None] | None = None):
        if budget < 1:
            raise ValueError("the evaluation budget must be at least 1")
        if seconds is not None and seconds <= 0:
            raise ValueError("the time budget must be positive (s)")
        self._evaluate = evaluate
        self.budget = int(budget)
        self.seconds = seconds
        self.path = Path(path) if path is not None else None
        self.progress = progress
        self.evaluations: list[Evaluation] = []
        self.phase = ""
        self.stopped = ""
        self.replayed = 0
        self._cache: dict[tuple, Evaluation] = {}
        self._limit = self.budget
        self._started = time.perf_counter()
        if self.path is not None:
            if self.path.exists() and not resume:
                raise FileExistsError(f"{self.path} exists: resume it (--resume) or choose another output folder")
            if resume and self.path.exists():
                text = self.path.read_text()
                if text and not text.endswith("\n"):  # a run killed mid-line: drop the half-written record
                    text = text[: text.rfind("\n") + 1]
                    write_text_atomically(self.path, text)
                for evaluation in read_evaluations(self.path):
                    self._cache.setdefault(tuple(evaluation.z), evaluation)

    @property
    def best(self) -> Evaluation | None:
        return min(self.evaluations, key=lambda e: e.objective, default=None)

    @property
    def remaining(self) -> int:
        return self._limit - len(self.evaluations)

    def limit(self, count: int | None) -> None:
        """End the current phase after ``count`` more evaluations (None: at the budget)."""
        self._limit = self.budget if count is None else min(self.budget, len(self.evaluations) + int(count))

    def __call__(self, positions) -> np.ndarray:
        """Objectives of unit positions (B, d). Raises :class:`BudgetExhausted` once the budget
        (of the phase), the time or a cancel stops the run; the positions evaluated before that
        are recorded."""
        positions = np.atleast_2d(np.asarray(positions, float))
        if self.remaining <= 0:
            self._stop("budget")
        if self.seconds is not None and time.perf_counter() - self._started > self.seconds:
            self._stop("time")
        positions = positions[: self.remaining]
        results: list[Evaluation | None] = [self._cache.get(tuple(float(v) for v in z)) for z in positions]
        new = [i for i, r in enumerate(results) if r is None]
        if new:
            for i, evaluation in zip(new, self._evaluate(positions[new])):
                results[i] = evaluation
        self.replayed += len(positions) - len(new)
        fresh = set(new)
        for i, evaluation in enumerate(results):
            self._record(evaluation, fresh=i in fresh)
        best = self.best
        if self.progress is not None and self.progress(len(self.evaluations), self.budget, best.objective,
                                                       self.phase) is False:
            self._stop("cancelled")
        return np.array([e.objective for e in results])

    def _record(self, evaluation: Evaluation, fresh: bool) -> None:
        self.evaluations.append(evaluation)
        # a position asked for again is answered from here, in a fresh run as in a resumed one: a
        # resumed run then solves the same batches as an uninterrupted one (a batch's solves
        # depend, in their last digits, on the models solved beside them)
        self._cache.setdefault(tuple(float(v) for v in evaluation.z), evaluation)
        if fresh and self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "a") as stream:
                stream.write(json.dumps({"index": len(self.evaluations) - 1, "phase": self.phase,
                                         **evaluation.to_dict()}) + "\n")
                stream.flush()
                os.fsync(stream.fileno())

    def _stop(self, reason: str) -> None:
        if reason != "budget" or self._limit == self.budget:
            self.stopped = reason
        raise BudgetExhausted(reason)
