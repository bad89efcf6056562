"""The candidate-effect library: each effect the fitted model may be missing is one class in
one file of this package (parameters with ranges and "off" values, how it changes a model
variant). Adding an effect is adding a file, its class to :func:`library` and to the names this
package exports (imported on first use, below).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from BreastBiomechLib.lazy import exports

if TYPE_CHECKING:
    from BreastBiomechLib.discrepancy.effects.base import Effect

NAMES = ("friction", "friction-per-plate", "gravity", "gravity-direction", "chest-wall", "skin", "anisotropy",
         "heterogeneity", "tumour", "plate-tilt", "plate-offset")


def library(fitted, names=None) -> list[Effect]:
    """The candidate effects for ``fitted`` (a :class:`~BreastBiomechLib.discrepancy.fitted.FittedCase`),
    those named in ``names`` (default all of :data:`NAMES`), sized to its plates and tissues."""
    names = NAMES if names is None else tuple(names)
    unknown = sorted(set(names) - set(NAMES))
    if unknown:
        raise ValueError(f"unknown effects {unknown}; the library has {list(NAMES)}")
    from BreastBiomechLib.discrepancy.effects.anisotropy import Anisotropy
    from BreastBiomechLib.discrepancy.effects.chest_wall import ChestWallHold
    from BreastBiomechLib.discrepancy.effects.friction import PlateFriction
    from BreastBiomechLib.discrepancy.effects.friction_per_plate import FrictionPerPlate
    from BreastBiomechLib.discrepancy.effects.gravity import GravityPrestress
    from BreastBiomechLib.discrepancy.effects.gravity_direction import GravityDirection
    from BreastBiomechLib.discrepancy.effects.heterogeneity import Heterogeneity
    from BreastBiomechLib.discrepancy.effects.plate_offset import PlateOffset
    from BreastBiomechLib.discrepancy.effects.plate_tilt import PlateTilt
    from BreastBiomechLib.discrepancy.effects.skin import SkinLayer
    from BreastBiomechLib.discrepancy.effects.tumour import TumourStiffness

    plates = max(len(fitted.plates), 1)
    made = {"friction": PlateFriction, "friction-per-plate": lambda: FrictionPerPlate(plates),
            "gravity": GravityPrestress, "gravity-direction": GravityDirection, "chest-wall": ChestWallHold,
            "skin": SkinLayer, "anisotropy": Anisotropy, "heterogeneity": lambda: Heterogeneity.for_fit(fitted),
            "tumour": TumourStiffness, "plate-tilt": lambda: PlateTilt(plates, offsets=not fitted.space.plates),
            "plate-offset": lambda: PlateOffset(plates)}
    return [made[name]() for name in NAMES if name in names]


__all__ = ["Effect", "EffectParameter", "NAMES", "library", "Anisotropy", "ChestWallHold", "PlateFriction",
           "FrictionPerPlate", "GravityPrestress", "GravityDirection", "Heterogeneity", "PlateOffset", "PlateTilt",
           "SkinLayer", "TumourStiffness"]

# the effects' classes are imported on first use (their modules import the solver and warp; see
# BreastBiomechLib.lazy), so that the command line lists NAMES without them
__getattr__, __dir__ = exports(__name__, {"Effect": "base", "EffectParameter": "base", "Anisotropy": "anisotropy",
                                          "ChestWallHold": "chest_wall", "PlateFriction": "friction",
                                          "FrictionPerPlate": "friction_per_plate", "GravityPrestress": "gravity",
                                          "GravityDirection": "gravity_direction", "Heterogeneity": "heterogeneity",
                                          "PlateOffset": "plate_offset", "PlateTilt": "plate_tilt",
                                          "SkinLayer": "skin", "TumourStiffness": "tumour"})
