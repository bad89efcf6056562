"""Tissue heterogeneity: glandular tissue (and muscle) stiffer or softer than fat, for a fit
that gave the whole breast one material."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from BreastBiomechLib import labels
from BreastBiomechLib.discrepancy.effects.base import Effect, EffectParameter
from BreastBiomechLib.discrepancy.effects.materials_common import stiffer
from BreastBiomechLib.discrepancy.variants import Variant

TISSUES = ("glandular", "muscle")


class Heterogeneity(Effect):
    """Per-tissue moduli in a homogeneous fit: each of glandular tissue and muscle (those the
    mesh holds) with its own stiffness, parameter ln(E_tissue / E_breast) (glandular tissue is
    1-4 x fat in the seed's Table 3)."""

    name = "heterogeneity"
    title = "tissue heterogeneity"
    acts_in = "the glandular tissue and the muscle"

    def __init__(self, tissues=TISSUES):
        self.tissues = tuple(tissues)
        self.parameters = tuple(EffectParameter(f"ln(E_{t}/E_breast)", "", 0.0, -2.5, 3.0, float(np.log(2.0)),
                                                f"{t} stiffness relative to the fitted breast material")
                                for t in self.tissues)

    @classmethod
    def for_fit(cls, fitted) -> "Heterogeneity":
        present = [t for t in TISSUES if np.any(fitted.tissue == labels.tissue(t).label)]
        return cls(present or TISSUES[:1])

    def unavailable(self, fitted) -> str | None:
        if not fitted.space.homogeneous:
            return "the fitted model already has a material per tissue"
        if not any(np.any(fitted.tissue == labels.tissue(t).label) for t in self.tissues):
            return "the mesh holds no glandular tissue or muscle"
        return None

    def apply(self, variant: Variant, values, fitted) -> Variant:
        materials = variant.materials
        for tissue, value in zip(self.tissues, values):
            materials = stiffer(materials, fitted.tissue == labels.tissue(tissue).label, value)
        return replace(variant, materials=materials)
