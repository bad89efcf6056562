"""A tilt of each plate's final plane against the plane measured in the compressed image."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from BreastBiomechLib.discrepancy.effects.base import Effect, EffectParameter
from BreastBiomechLib.discrepancy.variants import Variant
from BreastBiomechLib.solver.placement import posed_plate


class PlateTilt(Effect):
    """Each plate turned by two small angles about its tilt axes through its final point
    (:func:`~BreastBiomechLib.solver.placement.posed_plate`): the measured plate planes are
    uncertain by a degree or so where the plates are read off the image. Two parameters per
    plate (degrees)."""

    name = "plate-tilt"
    title = "plate tilt"
    acts_in = "the contact bands, growing towards the plates' far edges"

    def __init__(self, plates: int = 2):
        self.parameters = tuple(EffectParameter(f"plate{i + 1}.tilt{a + 1}", "deg", 0.0, -5.0, 5.0, 1.0,
                                                f"plate {i + 1}'s tilt about its axis {a + 1}")
                                for i in range(plates) for a in range(2))

    def unavailable(self, fitted) -> str | None:
        return "the case has no plates" if not fitted.plates else None

    def apply(self, variant: Variant, values, fitted) -> Variant:
        tilts = np.asarray(values, float).reshape(-1, 2)
        if len(tilts) != len(variant.plates):
            raise ValueError(f"plate tilt: {len(tilts)} tilts for {len(variant.plates)} plates")
        start = variant.model.start_positions
        plates = [posed_plate(p, start, t) if np.any(t) else p for p, t in zip(variant.plates, tilts)]
        return replace(variant, plates=plates)
