"""The chest wall holding the breast along itself, where the fitted model lets it slide.

The fitted model's chest wall is the seed's: its nodes held anterior-posteriorly only, so the
breast base slides freely along a chest that faces the anterior direction (the supports' tests:
sliding on a flat chest is that wall). What such a model can miss is the opposite: a chest wall
that holds the tissue on it (the pectoral muscle attached to the ribs, an adherent
retromammary fascia), which matters most where one plate moves and pushes the whole breast
towards the other (the seed's rig): a free base follows, a held one does not.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from BreastBiomechLib.discrepancy.effects.base import Effect, EffectParameter
from BreastBiomechLib.discrepancy.variants import Variant
from BreastBiomechLib.solver.model import SurfaceSupport
from BreastBiomechLib.solver.supports import surface_normals_and_areas

REFERENCE_STIFFNESS = 340.0  # Pa/mm: about fat's shear modulus (3.4 kPa) over a 10 mm layer


def hold_stiffness(hold: float) -> float:
    """The tangential spring stiffness (Pa/mm per area) of a chest-wall ``hold`` h in [0, 1):
    k_ref h / (1 - h), k_ref = :data:`REFERENCE_STIFFNESS` (0 free, 1 tied)."""
    return REFERENCE_STIFFNESS * hold / (1.0 - hold)


class ChestWallHold(Effect):
    """The chest wall's nodes keep the fit's anterior-posterior hold and gain springs along the
    local chest surface of k_ref h / (1 - h) Pa/mm per area (:func:`hold_stiffness`): h = 0 is the
    fit's chest wall (the breast free to slide on it, the nested case exactly), h = 0.9 about
    fat's shear modulus over a 1 mm layer, h -> 1 a tied chest wall. The field-of-view cut stays
    fixed."""

    name = "chest-wall"
    title = "chest-wall hold"
    acts_in = "the posterior band at the chest wall"
    own_model = True
    order = 2
    parameters = (EffectParameter("h", "", 0.0, 0.0, 0.99, 0.9,
                                  "hold of the chest wall along itself (0: free sliding, the fit's; 1: tied)"),)

    def unavailable(self, fitted) -> str | None:
        if "chest_wall" not in fitted.mesh.point_data or not len(fitted.mesh.node_set("chest_wall")):
            return "the fitting mesh has no chest-wall node set"
        return None

    def apply(self, variant: Variant, values, fitted) -> Variant:
        hold = float(np.clip(values[0], 0.0, self.parameters[0].upper))
        if hold == 0.0:
            return variant
        mesh = variant.model.mesh
        chest = mesh.node_set("chest_wall")
        normals, areas = surface_normals_and_areas(mesh, chest)
        stiffness = hold_stiffness(hold)
        springs = SurfaceSupport(chest, normals, areas, "elastic", 0.0, stiffness)
        loading = variant.model.loading
        loading = replace(loading, supports=list(loading.supports) + [springs],
                          notes=list(loading.notes) + [f"chest wall held along itself by {stiffness:.0f} Pa/mm "
                                                       f"(hold {hold:.2f}; {len(chest)} nodes)"])
        return replace(variant, model=replace(variant.model, loading=loading))
