"""Optimisers over the unit cube of a :class:`~BreastBiomechLib.optimisation.space.ParameterSpace`,
minimising the objective through an :class:`~BreastBiomechLib.optimisation.record.EvaluationLog`.

- ``hybrid``: the seed's search - simulated annealing for the global search (scipy's
  ``dual_annealing`` without its local steps, as MATLAB's ``simulannealbnd``), then a bounded
  quasi-Newton local search from the best point (L-BFGS-B, as ``fmincon``) whose forward-difference
  gradient is evaluated in one batched solve of d + 1 models.
- ``cmaes``: CMA-ES (the ``cma`` package) whose whole population is one batched solve.
- ``cmaes-local``: CMA-ES on whole generations within ``global_fraction`` of the budget, then
  the hybrid's local stage from the best point: for a budget of tens of solves (a CPU), where a
  few generations of CMA-ES are a best-of-random-draws and leave the fit unsettled.

Both are deterministic for a given ``seed``, which resume relies on.
"""

from __future__ import annotations

import numpy as np

from BreastBiomechLib.optimisation.record import BudgetExhausted, EvaluationLog

OPTIMISERS = ("hybrid", "cmaes", "cmaes-local")
GRADIENT_STEP = 0.01  # forward-difference step in the unit cube (a 10 % change of E over 4 decades)


def hybrid(log: EvaluationLog, start: np.ndarray, seed: int = 0, global_fraction: float = 0.6) -> None:
    """Simulated annealing on ``global_fraction`` of the budget from ``start``, then L-BFGS-B
    from the best point found on the rest."""
    from scipy.optimize import dual_annealing

    bounds = [(0.0, 1.0)] * len(start)
    log.phase = "global"
    log.limit(max(1, int(round(global_fraction * log.remaining))))
    try:
        dual_annealing(lambda z: float(log(z[None])[0]), bounds, x0=np.clip(start, 0, 1), seed=seed,
                       no_local_search=True, maxfun=10**9, maxiter=10**9)
    except BudgetExhausted:
        if log.stopped:
            return
    local(log, log.best.z if log.best else start)


def local(log: EvaluationLog, start: np.ndarray) -> None:
    """The local stage, on the rest of the budget: L-BFGS-B from ``start`` in the unit cube, its
    forward-difference gradient evaluated in one batched solve of d + 1 models."""
    from scipy.optimize import minimize

    d = len(start)
    bounds = [(0.0, 1.0)] * d
    log.phase = "local"
    log.limit(None)

    def value_and_gradient(z):
        step = np.where(z + GRADIENT_STEP <= 1.0, GRADIENT_STEP, -GRADIENT_STEP)
        points = np.vstack([z, z + np.diag(step)])
        values = log(points)
        if len(values) < d + 1:  # the budget ended inside the gradient
            raise BudgetExhausted("budget")
        return float(values[0]), (values[1:] - values[0]) / step

    try:
        minimize(value_and_gradient, start, jac=True, method="L-BFGS-B",
                 bounds=bounds, options={"maxfun": 10**9, "maxiter": 10**9, "ftol": 1e-9, "gtol": 1e-7})
    except BudgetExhausted:
        return


def cmaes_local(log: EvaluationLog, start: np.ndarray, seed: int = 0, population: int | None = None,
                global_fraction: float = 0.6) -> None:
    """:func:`cmaes` on whole generations of ``population`` (default 4 + 3 ln d) within
    ``global_fraction`` of the budget (one generation at least), then :func:`local` from its best
    point on the rest."""
    generation = population or 4 + int(3 * np.log(len(start)))
    log.limit(generation * max(1, int(global_fraction * log.remaining) // generation))
    cmaes(log, start, seed, population=population)
    if log.stopped or log.best is None:
        return
    local(log, np.asarray(log.best.z))


def cmaes(log: EvaluationLog, start: np.ndarray, seed: int = 0, sigma: float = 0.25,
          population: int | None = None) -> None:
    """CMA-ES from ``start`` with step size ``sigma`` (unit cube), ``population`` per generation
    (default 4 + 3 ln d), each generation one batched evaluation. CMA-ES needs two dimensions
    or more: one free parameter is searched by :func:`bracketing` instead."""
    import cma

    if len(start) == 1:
        bracketing(log, population or 8)
        return

    options = {"bounds": [0.0, 1.0], "seed": 1000 + seed, "verbose": -9, "maxfevals": 10**9,
               "tolfun": 1e-9, "tolx": 1e-6}
    if population is not None:
        options["popsize"] = int(population)
    strategy = cma.CMAEvolutionStrategy(np.clip(start, 0, 1).tolist(), sigma, options)
    log.phase = "cmaes"
    try:
        while not strategy.stop():
            candidates = strategy.ask()
            values = log(np.array(candidates))
            if len(values) < len(candidates):
                return
            strategy.tell(candidates, values.tolist())
    except BudgetExhausted:
        return


def bracketing(log: EvaluationLog, population: int = 8, tolerance: float = 1e-6) -> None:
    """A batched search of one parameter: ``population`` points spread evenly over the unit
    interval in one batch, then the same number inside the bracket around the best, shrinking
    the bracket ``population``/2-fold per batch until it is narrower than ``tolerance``."""
    if population < 3:
        raise ValueError("the bracketing search needs a population of at least 3")
    log.phase = "bracket"
    low, high = 0.0, 1.0
    points = np.linspace(low, high, population)
    known: dict[float, float] = {}
    try:
        while high - low > tolerance:
            fresh = [z for z in points if z not in known]
            for z, value in zip(fresh, log(np.array(fresh)[:, None])):
                known[z] = float(value)
            ordered = sorted(known)
            best = min(ordered, key=known.get)
            i = ordered.index(best)
            low, high = ordered[max(i - 1, 0)], ordered[min(i + 1, len(ordered) - 1)]
            points = np.linspace(low, high, population + 2)[1:-1]
    except BudgetExhausted:
        return
