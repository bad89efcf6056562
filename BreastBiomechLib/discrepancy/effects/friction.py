"""Coulomb friction between the skin and the compression plates (one coefficient for all plates)."""

from __future__ import annotations

from dataclasses import replace

from BreastBiomechLib.discrepancy.effects.base import Effect, EffectParameter
from BreastBiomechLib.discrepancy.variants import Variant


class PlateFriction(Effect):
    """Skin sticks to the plates while the tangential force is within mu times the normal force
    (:class:`~BreastBiomechLib.solver.model.Plate`): the skin under the plates slides less
    outwards than in the frictionless model. Skin on plastic: mu about 0.2-1."""

    name = "friction"
    title = "plate friction"
    acts_in = "the contact bands under the plates"
    parameters = (EffectParameter("mu", "", 0.0, 0.0, 1.5, 0.3, "Coulomb coefficient of skin on the plates"),)

    def unavailable(self, fitted) -> str | None:
        if not fitted.plates:
            return "the case has no plates"
        if any(p.friction > 0 for p in fitted.plates):
            return "the fitted model already has plate friction"
        return None

    def apply(self, variant: Variant, values, fitted) -> Variant:
        mu = max(float(values[0]), 0.0)
        return replace(variant, plates=[replace(p, friction=mu) for p in variant.plates])
