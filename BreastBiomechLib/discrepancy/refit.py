"""Adding a candidate effect and refitting: a bounded Gauss-Newton step of the nuisance and the
effect's parameters together from their sensitivities (warm start at the current fit), checked
by a forward solve at the step, halved while it does not lower the residual and, where it does
but by less than half of what the linearisation predicts for that step (a secant overshoots
where the effect saturates), while the shorter step lowers it further (the best of the trials
stands). Where every trial fails to solve or none lowers the residual, the best of the effect's
secant models (solved already for the sensitivities) stands if it lowers it: a second start
along the effect's own signature. Then, for the effect that is added, further Gauss-Newton
iterations from fresh sensitivities (:func:`refine`), since a secant from the off value is only
the first guess of a nonlinear effect's size.

The same step of the fitted parameters alone (the "effect" None) is the nested null model's
refit: a fit that had not quite converged on the diagnosis's features lowers its residual by
that step with no effect added, and an effect is only credited with what it removes beyond."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy.optimize import lsq_linear

from BreastBiomechLib.discrepancy.effects import Effect
from BreastBiomechLib.discrepancy.observations import Observations
from BreastBiomechLib.discrepancy.sensitivity import Sensitivities, sensitivities
from BreastBiomechLib.discrepancy.state import ModelState
from BreastBiomechLib.discrepancy.variants import Outcome, solve_variants
from BreastBiomechLib.timing import staged

HALVINGS = 3
TRIALS_TOGETHER = 2  # a Gauss-Newton step and its half solved at once where two models cost about one
ACCEPTED_RATIO = 0.5  # a step that removes at least this share of its predicted reduction stands


def _predicted_reduction(rss_before: float, rss_linear: float, fraction: float) -> float:
    """The linearised fall of the residual sum of squares at ``fraction`` of the full step (the
    model is quadratic in the step: (2f - f^2) times the full step's fall)."""
    return (2.0 * fraction - fraction ** 2) * max(rss_before - rss_linear, 0.0)


@dataclass
class Refit:
    """A refit with ``effect`` added (None: the fitted parameters alone): its ``values`` (effect
    units) and their standard deviations ``sd`` (from the linearised information), the refitted
    ``state``, whitened residual sums of squares ``rss_before`` and ``rss_after`` (solved) and
    ``rss_linear`` (predicted by the linearisation), the ``displacement`` (N, 3) mm after, the
    features' ``residual_after`` (mm), the solver's ``status``, a ``note`` on how it was made
    when not by the Gauss-Newton step, and the ``outcome`` of the solve it was checked by (None
    where it was not solved: a secant model's linear prediction, or kept from an earlier run)."""

    effect: Effect | None
    values: np.ndarray
    sd: np.ndarray
    state: ModelState
    rss_before: float
    rss_after: float
    rss_linear: float
    displacement: np.ndarray
    residual_after: np.ndarray
    status: str
    note: str = ""
    profile: list[dict] | None = None  # the added effect's profile intervals (discrepancy.profile)
    outcome: Outcome | None = field(default=None, repr=False, compare=False)

    @property
    def ok(self) -> bool:
        return self.status == "completed"


def _key(effect: Effect | None) -> str:
    return "" if effect is None else effect.name


def _step(state: ModelState, sens: Sensitivities, effect: Effect | None, weights: np.ndarray, residual: np.ndarray):
    nuisance = state.nuisance()
    a = weights[:, None] * sens.nuisance
    b = weights[:, None] * (sens.effects[effect.name] if effect else np.zeros((len(weights), 0)))
    design = np.hstack([a, b])
    off, low, high = (effect.off, effect.lower, effect.upper) if effect else ([], [], [])
    current = np.array([v for _, v, _, _ in nuisance] + list(off))
    lower = np.array([lo for _, _, lo, _ in nuisance] + list(low)) - current
    upper = np.array([hi for _, _, _, hi in nuisance] + list(high)) - current
    whitened = weights * residual
    solution = lsq_linear(design, whitened, bounds=(lower, upper))
    covariance = np.linalg.pinv(design.T @ design)
    sd = np.sqrt(np.maximum(np.diag(covariance)[len(nuisance):], 0.0))
    rss_linear = float(np.sum((whitened - design @ solution.x) ** 2))
    return current, solution.x, sd, rss_linear, len(nuisance)


@staged("refits")
def refit(state: ModelState, observations: Observations, sens: Sensitivities,
          effects: list[Effect | None]) -> list[Refit]:
    """Refit ``state`` with each of ``effects`` added (their sensitivities in ``sens``; None: no
    effect, the fitted parameters alone); the trial solves of all are made together, then halved
    one by one where needed."""
    weights = 1.0 / observations.sigma
    residual = observations.measured - sens.features
    rss_before = float(np.sum((weights * residual) ** 2))
    plans = [(effect, *_step(state, sens, effect, weights, residual)) for effect in effects]
    fraction = {_key(effect): 1.0 for effect in effects}
    best: dict[str, Refit] = {}  # the trial that lowered the residual most so far
    results: dict[str, Refit] = {}
    fitted = state.fitted
    for _ in range(HALVINGS + 1):
        pending = [plan for plan in plans if _key(plan[0]) not in results]
        if not pending:
            break
        trials, variants = [], []
        for effect, current, delta, sd, rss_linear, p in pending:
            values = current + fraction[_key(effect)] * delta
            trial = state.with_nuisance(values[:p])
            if effect is not None:
                trial = trial.with_effect(effect, values[p:])
            try:
                variants.append(trial.variant())
            except ValueError:
                fraction[_key(effect)] /= 2
                continue
            trials.append((effect, trial, values[p:], sd, rss_linear))
        outcomes = solve_variants(variants, fitted.mesh.nodes, fitted.relaxation, fitted.device)
        for (effect, trial, values, sd, rss_linear), outcome in zip(trials, outcomes):
            name = _key(effect)
            last = fraction[name] <= 0.5 ** HALVINGS
            if outcome.ok:
                after = observations.residual(outcome.displacement)
                rss_after = float(np.sum((weights * after) ** 2))
                if rss_after < (best[name].rss_after if name in best else rss_before):
                    # lower than before: keep it; where it fell short of the linearised fall, try
                    # the shorter step too (a step from the secant overshoots where the effect
                    # saturates, as a chest-wall hold does)
                    best[name] = Refit(effect, values, sd, trial, rss_before, rss_after, rss_linear,
                                       outcome.displacement, after, outcome.status, outcome=outcome)
                    predicted = _predicted_reduction(rss_before, rss_linear, fraction[name])
                    if last or rss_before - rss_after >= ACCEPTED_RATIO * predicted:
                        results[name] = best[name]
                    fraction[name] /= 2
                    continue
                if name in best or last:
                    results[name] = best.get(name) or Refit(effect, values, sd, trial, rss_before, rss_after,
                                                            rss_linear, outcome.displacement, after, outcome.status,
                                                            outcome=outcome)
                    continue
            elif name in best:
                results[name] = best[name]
                continue
            elif last:
                results[name] = Refit(effect, values, sd, trial, rss_before, float("inf"), rss_linear,
                                      sens.displacement, residual, outcome.status)
                continue
            fraction[name] /= 2
    results = best | results
    for effect, _, _, sd, rss_linear, _ in plans:
        if effect is None:
            continue
        failed = effect.name not in results or not results[effect.name].ok
        if failed or results[effect.name].rss_after >= rss_before:
            # a second start along the effect's own signature: its secant models were solved for
            # the sensitivities (no solve more), and a significant score test that the joint step
            # loses to the nonlinearity is a start to find, not an effect to drop
            secant = _best_secant(state, sens, effect, observations, weights, rss_before, sd, rss_linear,
                                  "every Gauss-Newton trial failed to solve" if failed
                                  else "no Gauss-Newton trial lowered the residual")
            if secant is not None:
                results[effect.name] = secant
    return [results[_key(e)] for e in effects if _key(e) in results]


def _best_secant(state: ModelState, sens: Sensitivities, effect: Effect, observations: Observations,
                 weights: np.ndarray, rss_before: float, sd: np.ndarray, rss_linear: float,
                 why: str) -> Refit | None:
    """The effect's secant model (one parameter at its sensitivity step, the rest and the fitted
    parameters as they are) that lowers the residual most, as a refit noted with ``why`` the
    Gauss-Newton step did not stand; None when none lowers it."""
    if effect.name not in sens.steps:
        return None
    best = None
    for j, step in enumerate(sens.steps[effect.name]):
        values = effect.off.copy()
        values[j] += step
        displacement = sens.displacement + sens.fields[effect.name][j] * step
        after = observations.residual(displacement)
        rss_after = float(np.sum((weights * after) ** 2))
        if rss_after < rss_before and (best is None or rss_after < best.rss_after):
            best = Refit(effect, values, sd, state.with_effect(effect, values), rss_before, rss_after, rss_linear,
                         displacement, after, "completed", f"{why}; the secant model of the sensitivities stands")
    return best


class Refined(NamedTuple):
    """:func:`refine`'s result: the ``state``, its solve (``outcome``), each parameter's standard
    deviation ``sd`` ({nuisance key: sd}, the parameter's units) and the last iteration's
    ``sensitivities`` (None with no iteration)."""

    state: ModelState
    outcome: Outcome
    sd: dict[str, float]
    sensitivities: Sensitivities | None


@staged("refits")
def refine(state: ModelState, observations: Observations, iterations: int = 1,
           progress: Callable[[str], None] | None = None, current: Outcome | None = None) -> Refined:
    """Gauss-Newton iterations of every fitted parameter of ``state`` (the fit's and the added
    effects'), each from fresh sensitivities and checked by a forward solve (halved while it does
    not lower the residual; stopped when it no longer does; where two models of a batch cost
    about one, :func:`side_by_side`, a step and its half are solved at once and the longer that
    lowers the residual taken): a :class:`Refined`, the standard
    deviations from the last iteration's linearised information ({} with no iteration).
    ``progress(message)`` is called before each batch of solves. ``current``: the solve of
    ``state`` where the caller has it (a refit's :attr:`Refit.outcome`; not solved again)."""
    say = progress or (lambda message: None)
    fitted = state.fitted
    weights = 1.0 / observations.sigma
    if current is None:
        current = solve_variants([state.variant()], fitted.mesh.nodes, fitted.relaxation, fitted.device)[0]
    if not current.ok:
        raise RuntimeError(f"the model to refine does not solve ({current.status}: {current.message})")
    rss = float(np.sum((weights * observations.residual(current.displacement)) ** 2))
    sd: dict[str, float] = {}
    sens = None
    for iteration in range(iterations):
        say(f"Gauss-Newton iteration {iteration + 1} of {iterations}: sensitivities")
        sens = sensitivities(state, observations, [], say, current=current)
        nuisance = state.nuisance()
        values = np.array([v for _, v, _, _ in nuisance])
        lower = np.array([lo for _, _, lo, _ in nuisance]) - values
        upper = np.array([hi for _, _, _, hi in nuisance]) - values
        design = weights[:, None] * sens.nuisance
        covariance = np.linalg.pinv(design.T @ design)
        sd = {key: float(np.sqrt(max(covariance[k, k], 0.0))) for k, (key, *_) in enumerate(nuisance)}
        delta = lsq_linear(design, weights * (observations.measured - sens.features), bounds=(lower, upper)).x
        improved = False
        together = TRIALS_TOGETHER if side_by_side(fitted.device) else 1
        for first in range(0, HALVINGS + 1, together):
            halvings = range(first, min(first + together, HALVINGS + 1))
            say(f"Gauss-Newton iteration {iteration + 1} of {iterations}: trial step "
                + " and ".join("1" if h == 0 else f"1/{2 ** h}" for h in halvings))
            trials = [state.with_nuisance(values + delta / 2 ** h) for h in halvings]
            outcomes = solve_variants([trial.variant() for trial in trials], fitted.mesh.nodes, fitted.relaxation,
                                      fitted.device, start=current)
            for trial, outcome in zip(trials, outcomes):  # the longest step that lowers the residual
                if outcome.ok:
                    trial_rss = float(np.sum((weights * observations.residual(outcome.displacement)) ** 2))
                    if trial_rss < rss:
                        state, current, rss, improved = trial, outcome, trial_rss, True
                        break
            if improved:
                break
        if not improved:
            break
    return Refined(state, current, sd, sens)


def side_by_side(device) -> bool:
    """Whether two models of one batch take about the time of one on warp ``device``: a GPU (one
    launch), or a CPU whose batches are split over two or more worker processes
    (:func:`~BreastBiomechLib.solver.cpu_pool.cpu_workers`)."""
    import warp as wp

    from BreastBiomechLib.solver.cpu_pool import cpu_workers

    wp.init()
    return not wp.get_device(device).is_cpu or cpu_workers(TRIALS_TOGETHER) >= TRIALS_TOGETHER
