"""Gravity: the imaged breast is loaded by its weight, and the compression starts from that
pre-stressed state rather than from a stress-free one."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from BreastBiomechLib.discrepancy.effects.base import Effect, EffectParameter
from BreastBiomechLib.discrepancy.variants import Variant

STANDARD_GRAVITY = 9.81  # m/s^2


class GravityPrestress(Effect):
    """The compression solved from the breast's gravity-loaded state: its stress-free shape
    estimated from the imaged one (:func:`~BreastBiomechLib.solver.unloaded.unloaded_shape`)
    under s x 9.81 m/s^2 along the imaging posture's gravity (the fit's ``imaged_gravity``;
    prone MR: anterior), gravity acting through the compression. The moduli are scaled to fat's
    10 kPa reference, which the plates' prescribed motion cannot see but gravity can: s is
    therefore also 10 kPa / E_fat, and s = 2 means a breast half as stiff as the reference."""

    name = "gravity"
    title = "gravity pre-stress (unloaded state)"
    acts_in = "the whole breast, most where it hangs furthest from the chest wall"
    own_model = True
    order = 9
    parameters = (EffectParameter("s", "x 9.81 m/s^2", 0.0, 0.0, 3.0, 1.0,
                                  "gravity, or fat's 10 kPa over its real modulus"),)

    def unavailable(self, fitted) -> str | None:
        if not np.any(fitted.imaged_gravity):
            return "the imaging posture's gravity is not known"
        return None

    def apply(self, variant: Variant, values, fitted) -> Variant:
        from BreastBiomechLib.solver.unloaded import prestressed_model, unloaded_shape

        s = float(values[0])
        if s <= 0.0:
            return variant
        gravity = s * STANDARD_GRAVITY * np.asarray(fitted.imaged_gravity, float) / np.linalg.norm(fitted.imaged_gravity)
        model = replace(variant.model, materials=variant.materials,
                        loading=replace(variant.model.loading, plates=variant.plates))
        unloaded = unloaded_shape(model, gravity, tolerance_mm=0.05, device=fitted.device, relaxation=fitted.relaxation)
        loaded = prestressed_model(model, unloaded)
        return Variant(loaded, variant.materials, loaded.loading.plates)
