"""Plate friction that differs between the plates: the model's Coulomb coefficients shared out
unequally, their geometric mean kept."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from BreastBiomechLib.discrepancy.effects.base import Effect, EffectParameter, switched_on
from BreastBiomechLib.discrepancy.variants import Variant

RATIO_STEP = float(np.log(3.0))  # the secant's step: one plate's mu three times another's


class FrictionPerPlate(Effect):
    """Each plate's friction coefficient scaled by its own factor, the factors' geometric mean 1:
    with P plates, P - 1 parameters d_i = ln(mu_i / mu_P) (no unit; 0: the plates alike, the
    model as it is). Two plates of different material (a biopsy grid and a solid paddle, a
    detector cover and a compression paddle) hold the skin differently, and one wet plate slides
    where a dry one sticks.

    It refines the friction the model has, so it is a candidate only once the model has plate
    friction (the fit's own, or the friction candidate added in an earlier round): one
    coefficient for all plates is the candidate first tested (one degree of freedom, the most
    power where the plates are alike, and one secant model), and where it was added this tests
    whether the data ask the plates to differ (a further secant model per plate but one, solved
    from rest as every model with friction is). Applied after the friction candidate (``order``)."""

    name = "friction-per-plate"
    title = "friction differing between the plates"
    acts_in = "the contact band under each plate"
    order = 1

    def __init__(self, plates: int = 2):
        self.parameters = tuple(EffectParameter(f"ln(mu{i + 1}/mu{plates})", "", 0.0, -4.0, 4.0, RATIO_STEP,
                                                f"the log ratio of plate {i + 1}'s friction to plate {plates}'s")
                                for i in range(max(plates - 1, 1)))

    def unavailable(self, fitted) -> str | None:
        return self.unavailable_at(fitted, {})

    def unavailable_at(self, fitted, added) -> str | None:
        if len(fitted.plates) < 2:
            return "the case has fewer than two plates"
        if any(p.friction > 0 for p in fitted.plates):
            if all(p.friction > 0 for p in fitted.plates):
                return None
            return "the fit has friction on some plates only: their ratio to a frictionless plate is undefined"
        if switched_on(added, "friction"):
            return None
        return "the model has no plate friction yet: the friction candidate (one mu for all plates) comes first"

    def apply(self, variant: Variant, values, fitted) -> Variant:
        values = np.asarray(values, float)
        if len(values) != len(variant.plates) - 1:
            raise ValueError(f"friction per plate: {len(values)} log ratios for {len(variant.plates)} plates "
                             f"(one fewer than the plates)")
        factors = plate_factors(values)
        return replace(variant, plates=[replace(p, friction=p.friction * f) for p, f in zip(variant.plates, factors)])

    def describe(self, values) -> str:
        factors = plate_factors(np.asarray(values, float))
        return ", ".join(f"plate {i + 1}'s mu x{f:.3g}" for i, f in enumerate(factors))


def plate_factors(log_ratios: np.ndarray) -> np.ndarray:
    """(P,) each plate's factor on the shared coefficient for the P - 1 ``log_ratios``
    ln(mu_i / mu_P): exp of each plate's log coefficient less their mean (geometric mean 1)."""
    logs = np.append(np.asarray(log_ratios, float), 0.0)
    return np.exp(logs - logs.mean())
