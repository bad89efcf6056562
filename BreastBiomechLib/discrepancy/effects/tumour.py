"""A tumour stiffer than the tissue around it, where the fit did not search its modulus."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from BreastBiomechLib import labels
from BreastBiomechLib.discrepancy.effects.base import Effect, EffectParameter
from BreastBiomechLib.discrepancy.effects.materials_common import stiffer
from BreastBiomechLib.discrepancy.variants import Variant


class TumourStiffness(Effect):
    """The tumour's moduli scaled by exp(parameter) from the fitted ones (carcinomas are 3-10 x
    fat)."""

    name = "tumour"
    title = "tumour stiffness"
    acts_in = "the tumour and the tissue around it"
    parameters = (EffectParameter("ln(E_tumour/E_fitted)", "", 0.0, -1.0, 3.5, float(np.log(3.0)),
                                  "tumour stiffness relative to its fitted material"),)

    def unavailable(self, fitted) -> str | None:
        if not np.any(fitted.tissue == labels.TUMOUR.label):
            return "the mesh holds no tumour"
        if "tumour.E" in fitted.space.keys:
            return "the fit already searched the tumour's modulus"
        return None

    def apply(self, variant: Variant, values, fitted) -> Variant:
        return replace(variant, materials=stiffer(variant.materials, fitted.tissue == labels.TUMOUR.label, values[0]))
