"""An offset of each plate's final plane along its normal against the measured plane."""

from __future__ import annotations

from dataclasses import replace

from BreastBiomechLib.discrepancy.effects.base import Effect, EffectParameter
from BreastBiomechLib.discrepancy.variants import Variant


class PlateOffset(Effect):
    """Each plate's final position moved along its normal (mm, > 0: further into the tissue,
    more compression): a plate read off the image a voxel or two from where it was."""

    name = "plate-offset"
    title = "plate offset"
    acts_in = "the whole breast along the compression axis, most under the plates"

    def __init__(self, plates: int = 2):
        self.parameters = tuple(EffectParameter(f"plate{i + 1}.offset", "mm", 0.0, -5.0, 5.0, 1.0,
                                                f"plate {i + 1}'s offset along its normal")
                                for i in range(plates))

    def unavailable(self, fitted) -> str | None:
        if not fitted.plates:
            return "the case has no plates"
        if fitted.space.plates:
            return "the fit already searched the plate offsets"
        return None

    def apply(self, variant: Variant, values, fitted) -> Variant:
        if len(values) != len(variant.plates):
            raise ValueError(f"plate offset: {len(values)} offsets for {len(variant.plates)} plates")
        return replace(variant, plates=[offset_plate(p, v) for p, v in zip(variant.plates, values)])

    def column_key(self, j: int):
        return offset_key(j, self.parameters[j])


def offset_plate(plate, offset_mm: float):
    """``plate`` with its final position moved ``offset_mm`` along its normal, its start kept."""
    return replace(plate, displacement=plate.displacement + float(offset_mm) * plate.normal)


def offset_key(plate: int, parameter: EffectParameter) -> tuple:
    """The identity of a secant model that moves plate ``plate`` alone along its normal by
    ``parameter``'s step (:meth:`Effect.column_key`): the plate tilt's offsets share it."""
    return ("plate offset", plate, parameter.stepped(parameter.off))
