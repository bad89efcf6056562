"""A skin layer stiffer than the tissue under it, of unknown stiffness and thickness."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from BreastBiomechLib.discrepancy.effects.base import Effect, EffectParameter
from BreastBiomechLib.discrepancy.variants import Variant
from BreastBiomechLib.labels import SKIN

# the two shells under the skin surface the candidate stiffens, depths in mm: skin is 1-3 mm thick
SHELLS_MM = ((0.0, 1.5), (1.5, 3.0))


class SkinLayer(Effect):
    """The tissue in two shells under the skin surface (:data:`SHELLS_MM`: 0-1.5 and 1.5-3 mm
    deep) stiffened, each by its own factor exp(parameter), by partial-volume (Voigt) weighting of
    the elements the shells cross (:mod:`BreastBiomechLib.mesh.skin`). A skin of any thickness in
    1-3 mm and any stiffness is, to first order, a combination of the two: a thin stiff skin
    stiffens the outer shell alone, a 3 mm one both; a single layer of fixed thickness would
    miss a skin thinner or thicker than itself (issue 77, point 5). Skin is 5-50 x fat."""

    name = "skin"
    title = "skin layer"
    acts_in = "a band under the skin surface"
    order = 1
    parameters = tuple(EffectParameter(f"ln(E/E_tissue) {low:g}-{high:g} mm", "", 0.0, 0.0, 4.0, float(np.log(5.0)),
                                       f"stiffness of the tissue {low:g}-{high:g} mm under the skin relative to "
                                       "the tissue's own")
                       for low, high in SHELLS_MM)

    def unavailable(self, fitted) -> str | None:
        if np.any(fitted.tissue == SKIN.label):
            return "the mesh has skin elements of its own"
        return None

    @staticmethod
    def shells(fitted) -> list[np.ndarray]:
        """Each element's share (M,) of its volume in each shell of :data:`SHELLS_MM`."""
        return [fitted.skin_fraction(high) - (fitted.skin_fraction(low) if low > 0 else 0.0) for low, high in SHELLS_MM]

    def apply(self, variant: Variant, values, fitted) -> Variant:
        values = np.asarray(values, float)
        if values.shape != (len(SHELLS_MM),):
            raise ValueError(f"skin layer: {values.size} values for its {len(SHELLS_MM)} shells")
        f = sum(share * np.expm1(v) for share, v in zip(self.shells(fitted), values))
        materials = variant.materials
        return replace(variant, materials=replace(materials, mu=materials.mu * (1 + f), kappa=materials.kappa * (1 + f)))

    def describe(self, values) -> str:
        return ", ".join(f"x{np.exp(v):.3g} stiffer {low:g}-{high:g} mm under the skin"
                         for (low, high), v in zip(SHELLS_MM, values))
