"""A plate's final pose against the one measured in the compressed image: turned, and moved along
its normal, as a rigid motion about a pivot nobody knows."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from BreastBiomechLib.discrepancy.effects.base import Effect, EffectParameter
from BreastBiomechLib.discrepancy.effects.plate_offset import offset_key, offset_plate
from BreastBiomechLib.discrepancy.variants import Variant
from BreastBiomechLib.solver.placement import posed_plate


class PlateTilt(Effect):
    """Each plate turned by two small angles about its tilt axes through its final point
    (:func:`~BreastBiomechLib.solver.placement.posed_plate`; degrees) and, with ``offsets``, moved
    along its normal (mm, > 0 into the tissue): the measured plate planes are uncertain by a
    degree or so where the plates are read off the image, and a paddle turns about its mount,
    not about the point its plane was recorded at. A turn about any pivot is the turn about the
    final point followed by a move along the normal (and in the plane, which a plate's flat face
    does not feel), so tilts and offsets together span the plate's pose whatever the pivot
    (issue 77, point 5). Without ``offsets`` (a fit that searched the plate offsets has them
    already among its parameters) two parameters per plate, else three."""

    name = "plate-tilt"
    title = "plate tilt"
    acts_in = "the contact bands, growing towards the plates' far edges"

    def __init__(self, plates: int = 2, offsets: bool = True):
        self.offsets = bool(offsets)
        per_plate = []
        for i in range(plates):
            per_plate += [EffectParameter(f"plate{i + 1}.tilt{a + 1}", "deg", 0.0, -5.0, 5.0, 1.0,
                                          f"plate {i + 1}'s tilt about its axis {a + 1}") for a in range(2)]
            if self.offsets:
                per_plate.append(EffectParameter(f"plate{i + 1}.offset", "mm", 0.0, -5.0, 5.0, 1.0,
                                                 f"plate {i + 1}'s move along its normal with the tilt"))
        self.parameters = tuple(per_plate)

    @property
    def per_plate(self) -> int:
        return 3 if self.offsets else 2

    def unavailable(self, fitted) -> str | None:
        return "the case has no plates" if not fitted.plates else None

    def apply(self, variant: Variant, values, fitted) -> Variant:
        poses = np.asarray(values, float).reshape(-1, self.per_plate)
        if len(poses) != len(variant.plates):
            raise ValueError(f"plate tilt: {len(poses)} poses for {len(variant.plates)} plates")
        start = variant.model.start_positions
        plates = []
        for plate, pose in zip(variant.plates, poses):
            offset = pose[2] if self.offsets else 0.0
            if np.any(pose[:2]):
                plate = posed_plate(plate, start, pose[:2], offset_mm=offset)
            elif offset:  # untilted: the plate offset's own move, so that the two share their secant models
                plate = offset_plate(plate, offset)
            plates.append(plate)
        return replace(variant, plates=plates)

    def column_key(self, j: int):
        if not self.offsets or j % self.per_plate != 2:
            return None
        return offset_key(j // self.per_plate, self.parameters[j])
