"""A skin layer stiffer than the tissue under it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from BreastBiomechLib.discrepancy.effects.base import Effect, EffectParameter
from BreastBiomechLib.discrepancy.variants import Variant
from BreastBiomechLib.labels import SKIN

THICKNESS_MM = 2.0  # skin is 1-3 mm thick over the breast


class SkinLayer(Effect):
    """A layer of :data:`THICKNESS_MM` under the skin surface whose moduli are exp(parameter)
    times the tissue's, by partial-volume (Voigt) weighting of the elements it crosses
    (:mod:`BreastBiomechLib.mesh.skin`, as a case file's ``skin``). Skin is 5-20 x fat."""

    name = "skin"
    title = "skin layer"
    acts_in = "a band under the skin surface"
    order = 1
    parameters = (EffectParameter("ln(E_skin/E_tissue)", "", 0.0, 0.0, 4.0, float(np.log(5.0)),
                                  f"stiffness of a {THICKNESS_MM:g} mm skin layer relative to the tissue under it"),)

    def unavailable(self, fitted) -> str | None:
        if np.any(fitted.tissue == SKIN.label):
            return "the mesh has skin elements of its own"
        return None

    def apply(self, variant: Variant, values, fitted) -> Variant:
        f = fitted.skin_fraction(THICKNESS_MM) * (np.exp(float(values[0])) - 1.0)
        materials = variant.materials
        return replace(variant, materials=replace(materials, mu=materials.mu * (1 + f), kappa=materials.kappa * (1 + f)))
