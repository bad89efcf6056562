"""The design's best acquisitions checked beyond the linearisation: the fitted parameters refitted
to the data the effect would make.

A separation is linear: the effect's signature at the fit, beyond the span of the fitted
parameters' sensitivities there. Where a fitted parameter takes an effect up nonlinearly (the
chest-wall hold as a pectoral muscle that stiffens further: the two-state suite of 2026-12-08
realised 0.26-0.41 of the separations the design predicted for it), the joint fit of both scans
moves that parameter further than one linear step and takes up more. The check makes the data
the effect at its realistic size would give in the measured states and in the acquisition (each
state's features plus the effect's secant change there, from the solves the design has), refits
the model without the effect to them by Gauss-Newton steps whose Jacobian is the stacked
sensitivities at the fit, updated after each step by Broyden's rank-one rule from the change the
solve shows (no further sensitivity solves: each step solves the model in each state once), and
takes the separation as the length of what the refit leaves beyond the fitted parameters'
(updated) span and the rival's signature, in sigma of the noise model, as the diagnosis of both
scans would see it.

Units: features in mm, whitened by each feature's sigma; parameters in the diagnosis's nuisance
coordinates (:meth:`~BreastBiomechLib.discrepancy.state.ModelState.nuisance`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from BreastBiomechLib.discrepancy.observations import Observations
from BreastBiomechLib.discrepancy.sensitivity import Sensitivities
from BreastBiomechLib.discrepancy.state import ModelState
from BreastBiomechLib.discrepancy.variants import solve_variants

ITERATIONS = 3  # refit steps of a check, each one solve of the model in every state


def broyden_refit(residual_of: Callable[[np.ndarray], np.ndarray | None], residual: np.ndarray,
                  jacobian: np.ndarray, start: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                  iterations: int = ITERATIONS) -> dict:
    """Least squares of the whitened ``residual_of`` (theta -> y - f(theta), (n,); None where the
    model does not solve) from ``start`` (p,), whose ``residual`` is known, by Gauss-Newton steps
    within [``lower``, ``upper``] with the Jacobian of f (``jacobian`` (n, p) at the start)
    updated after each step by Broyden's rank-one rule. Returns the best point's {"theta",
    "residual", "jacobian" (the updated one), "steps" (taken), "rss" (each point's, the start's
    first), "stopped" (why it ended early, else None)}."""
    theta, r, J = np.asarray(start, float).copy(), np.asarray(residual, float), np.asarray(jacobian, float).copy()
    best = {"theta": theta, "residual": r, "jacobian": J}
    rss, stopped = [float(r @ r)], None
    for _ in range(iterations):
        step, *_ = np.linalg.lstsq(J, r, rcond=None)
        moved = np.clip(theta + step, lower, upper)
        taken = moved - theta
        if not np.any(taken):
            stopped = "at the parameters' bounds"
            break
        after = residual_of(moved)
        if after is None:
            stopped = "the model did not solve at the next step"
            break
        J = J + np.outer((r - after) - J @ taken, taken) / float(taken @ taken)
        theta, r = moved, after
        rss.append(float(r @ r))
        if rss[-1] <= min(rss[:-1]):
            best = {"theta": theta, "residual": r, "jacobian": J}
    return {**best, "steps": len(rss) - 1, "rss": rss, "stopped": stopped}


def refitted_separation(state: ModelState, placed: ModelState, measured: Observations, simulated: Observations,
                        now: Sensitivities, there: Sensitivities, jacobian: np.ndarray, effect: str,
                        rival_signature: np.ndarray | None, iterations: int = ITERATIONS) -> dict:
    """The separation (sigma) of ``effect`` in the measured states (``state`` at the fit, its
    features ``measured``, its sensitivities ``now``) with an acquisition (the model ``placed``
    with its plates, its features ``simulated``, its sensitivities ``there``) once the fitted
    parameters are refitted to the data the effect at its realistic size would make in both
    (:func:`broyden_refit`; ``jacobian`` (n, p) the stacked whitened sensitivities of the
    nuisance parameters, in :meth:`ModelState.nuisance`'s order; ``rival_signature`` (n,) the
    rival's stacked whitened signature, None: no rival). Returns {"sigma", "moved" {key: change},
    "steps", "solves", "rss", "stopped"}."""
    weights = np.concatenate([1.0 / measured.sigma, 1.0 / simulated.sigma])
    data = np.concatenate([now.features + now.effects[effect] @ now.steps[effect],
                           there.features + there.effects[effect] @ there.steps[effect]])
    keys, *bounds = zip(*state.nuisance())
    start, lower, upper = (np.asarray(column, float) for column in bounds)
    solves = [0]

    def residual_of(theta: np.ndarray) -> np.ndarray | None:
        variants = [state.with_nuisance(theta).variant(), placed.with_nuisance(theta).variant()]
        fitted = state.fitted
        outcomes = solve_variants(variants, fitted.mesh.nodes, fitted.relaxation, fitted.device)
        solves[0] += sum(o.attempts for o in outcomes)
        if not all(o.ok for o in outcomes):
            return None
        predicted = np.concatenate([measured.predicted(outcomes[0].displacement),
                                    simulated.predicted(outcomes[1].displacement)])
        return weights * (data - predicted)

    start_residual = weights * (data - np.concatenate([now.features, there.features]))
    made = broyden_refit(residual_of, start_residual, jacobian, start, lower, upper, iterations)
    span = made["jacobian"] if rival_signature is None else np.column_stack([made["jacobian"], rival_signature])
    coefficients, *_ = np.linalg.lstsq(span, made["residual"], rcond=None)
    left = made["residual"] - span @ coefficients
    return {"sigma": float(np.linalg.norm(left)),
            "moved": {k: float(v) for k, v in zip(keys, made["theta"] - start) if v != 0.0},
            "steps": made["steps"], "solves": solves[0], "rss": made["rss"], "stopped": made["stopped"]}
