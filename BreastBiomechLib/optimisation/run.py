"""Run an optimisation: the chosen optimiser over a :class:`FittingProblem`, with a budget,
progress and cancel, a results folder written as it goes, and resume.

Results folder::

    settings.json      the parameter space, optimiser, seed, budget and objective (checked on resume)
    evaluations.jsonl  every evaluation, one JSON object per line, appended as it is made
    warm_starts/       the equilibrium the next batch starts at (see optimisation/warm_starts.py)
    result.json        the best evaluation, its materials, the stop reason and the figures
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from BreastBiomechLib.io.atomic import write_json_atomically
from BreastBiomechLib.io.claims import claimed
from BreastBiomechLib.optimisation import search
from BreastBiomechLib.optimisation.forward import Evaluation, FittingProblem
from BreastBiomechLib.optimisation.record import EvaluationLog, read_evaluations


SETTLED = 1e-3  # a best objective (-NMI) falling less than this over a fit's last half of solves: settled


@dataclass
class OptimisationResult:
    """``best``: the best evaluation; ``materials``: every material's {"E", "nu", "eta"} there;
    ``evaluations``: all, in order; ``stopped``: why the run ended ("converged", "budget",
    "time", "cancelled"); ``replayed``: evaluations answered without a solve (from a resumed
    results file, or a position asked for again); ``seconds``: wall time of this run;
    ``geometry``: the free fibre direction and plate offsets there
    (:meth:`ParameterSpace.geometry`; empty when none is free); ``stand_in``: empty, or why ``best`` is not the best evaluation (see :func:`solve_best`)."""

    best: Evaluation
    materials: dict[str, dict[str, float]]
    evaluations: list[Evaluation]
    stopped: str
    replayed: int
    seconds: float
    geometry: dict = field(default_factory=dict)
    stand_in: dict = field(default_factory=dict)

    def recent_gain(self, share: float = 0.5) -> float:
        """How far the best objective fell over the last ``share`` of the evaluations (objective
        units, >= 0; inf where nothing had completed before them, NaN with fewer than two
        evaluations): about 0 where the search had settled, more where the fit was still
        improving when its budget ended (an unfinished fit)."""
        objectives = [e.objective if e.status == "completed" else np.inf for e in self.evaluations]
        if len(objectives) < 2:
            return float("nan")
        best = np.minimum.accumulate(objectives)
        before = best[max(1, int(round(len(best) * (1.0 - share)))) - 1]
        return float(before - best[-1]) if np.isfinite(before) else float("inf")

    @property
    def failures(self) -> dict[str, int]:
        """How many evaluations failed, by the solver's status ("inverted elements", "not
        converged", ...); each one's reason is its ``message``."""
        counts: dict[str, int] = {}
        for e in self.evaluations:
            if e.status != "completed":
                counts[e.status] = counts.get(e.status, 0) + 1
        return counts

    def summary(self) -> dict:
        return {"best": self.best.to_dict(), "materials": self.materials, "geometry": self.geometry,
                "stopped": self.stopped,
                "evaluations": len(self.evaluations), "replayed": self.replayed,
                "failed": sum(self.failures.values()), "failures": self.failures,
                "seconds": round(self.seconds, 2),
                **({"stand_in": self.stand_in} if self.stand_in else {})}


def optimise(problem: FittingProblem, optimiser: str = "hybrid", budget: int = 500, seconds: float | None = None,
             seed: int = 0, out_dir: str | Path | None = None, resume: bool = False,
             progress: Callable[[int, int, float, str], bool | None] | None = None,
             start: dict[str, float] | None = None, population: int | None = None) -> OptimisationResult:
    """Minimise ``problem``'s objective over its parameter space with ``optimiser`` ("hybrid",
    "cmaes" or "cmaes-local", :mod:`~BreastBiomechLib.optimisation.search`) from ``start`` ({"tissue.name": value}; default :meth:`ParameterSpace.start`:
    the middle of the material parameters' ranges, the given fibre and plates),
    within ``budget`` evaluations and ``seconds`` of wall time. With ``out_dir`` every
    evaluation is written as it is made, and ``resume`` continues a run interrupted there (the
    same settings replay to where it stopped). ``progress(done, budget, best objective, phase)``
    returning False cancels (the results so far are kept)."""
    if optimiser not in search.OPTIMISERS:
        raise ValueError(f"unknown optimiser {optimiser!r}; choose one of {search.OPTIMISERS}")
    space = problem.space
    if space.dimension == 0:
        raise ValueError("no parameter is free: choose at least one to optimise")
    z0 = space.unit(start) if start else space.start()
    settings = {"space": space.to_dict(), "optimiser": optimiser, "seed": int(seed), "budget": int(budget),
                "objective": problem.objective, "start": [float(v) for v in z0], "population": population}
    with claimed(out_dir, "an optimisation"):
        path = None
        if out_dir is not None:
            out = Path(out_dir)
            out.mkdir(parents=True, exist_ok=True)
            path = out / "evaluations.jsonl"
            settings_path = out / "settings.json"
            if resume and settings_path.exists():
                before = json.loads(settings_path.read_text())
                changed = sorted(k for k in settings if k != "budget" and before.get(k) != settings[k])
                if changed:
                    raise ValueError(f"{out}: cannot resume with other settings ({', '.join(changed)} differ); "
                                     "resume with the same ones or start a new output folder")
            write_json_atomically(settings_path, settings)
        started = time.perf_counter()
        log = EvaluationLog(problem.evaluate, budget, seconds, path, resume, progress)
        problem.start_fit(None if out_dir is None else Path(out_dir) / "warm_starts",
                          read_evaluations(path) if resume and path is not None and path.exists() else [])
        if optimiser == "hybrid":
            search.hybrid(log, z0, seed)
        elif optimiser == "cmaes-local":
            search.cmaes_local(log, z0, seed, population=population)
        else:
            search.cmaes(log, z0, seed, population=population)
        if log.best is None:
            raise RuntimeError("the optimisation stopped before its first evaluation")
        result = OptimisationResult(log.best, space.materials(log.best.z), log.evaluations,
                                    log.stopped or ("budget" if len(log.evaluations) >= budget else "converged"),
                                    log.replayed, time.perf_counter() - started, space.geometry(log.best.z))
        if out_dir is not None:
            write_json_atomically(Path(out_dir) / "result.json", result.summary())
        return result


STAND_IN_TRIES = 5  # next-best evaluations tried when the best no longer solves alone


def solve_best(problem: FittingProblem, result: OptimisationResult, out_dir: str | Path | None = None,
               tries: int = STAND_IN_TRIES) -> tuple[OptimisationResult, object]:
    """The fit's best parameters solved alone, as its outputs are made from them: the result and
    the :class:`~BreastBiomechLib.solver.Solution`. The best was solved in a batch; alone (even
    with the slower loads of :meth:`FittingProblem.solve_alone`) a marginal model can still invert
    an element. Then the next best completed evaluations stand in, in order of objective, ``tries``
    at most: the first that solves becomes the result's best, its ``stand_in`` names the best
    that did not solve and why, and ``out_dir``'s result.json is rewritten. Raises RuntimeError
    when none solves."""
    others = (e for e in result.evaluations if e.status == "completed" and e is not result.best)
    ranked = [result.best] + sorted(others, key=lambda e: e.objective)
    failures = []
    for evaluation in ranked[:1 + tries]:
        solution = problem.solve_alone(evaluation.z)
        if solution.ok:
            break
        failures.append(f"objective {evaluation.objective:.6g}: {solution.message}")
    else:
        raise RuntimeError(f"the best parameters no longer solve alone, nor the {len(failures) - 1} next best "
                           f"({'; '.join(failures)})")
    if evaluation is result.best:
        return result, solution
    space = problem.space
    stand_in = {"best_objective": result.best.objective, "objective": evaluation.objective,
                "rank": len(failures) + 1, "reason": "; ".join(failures)}
    result = OptimisationResult(evaluation, space.materials(evaluation.z), result.evaluations,
                                result.stopped, result.replayed, result.seconds,
                                space.geometry(evaluation.z), stand_in)
    if out_dir is not None:
        write_json_atomically(Path(out_dir) / "result.json", result.summary())
    return result, solution
