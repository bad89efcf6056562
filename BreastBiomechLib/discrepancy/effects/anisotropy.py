"""Transversely isotropic tissue: a fibre family along the fit's fibre direction, for an
isotropic fit."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from BreastBiomechLib.discrepancy.effects.base import Effect, EffectParameter
from BreastBiomechLib.discrepancy.variants import Variant


class Anisotropy(Effect):
    """The seed's transversely isotropic neo-Hookean model in every element: fibre stiffness eta
    (Pa) along the fit's fibre direction (the ``--fibre`` of the fit, LPS; default SI, the
    seed's). The direction stays that of the fit: at eta = 0 it has no effect, so a score at
    the fitted model cannot see it; a refit of an anisotropic variant searches it."""

    name = "anisotropy"
    title = "anisotropy (fibre stiffness)"
    acts_in = "the whole breast, along the fibre direction"
    parameters = (EffectParameter("eta", "Pa", 0.0, 0.0, 1e5, 5e3, "fibre stiffness along the fibre direction"),)

    def unavailable(self, fitted) -> str | None:
        return "the fitted model is already anisotropic" if fitted.space.anisotropic else None

    def apply(self, variant: Variant, values, fitted) -> Variant:
        eta = max(float(values[0]), 0.0)
        fibre = np.broadcast_to(np.asarray(fitted.space.fibre, float), variant.materials.fibre.shape)
        return replace(variant, materials=replace(variant.materials, eta=np.full_like(variant.materials.eta, eta),
                                                  fibre=fibre.copy()))
