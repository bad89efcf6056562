"""The breast sliding on the chest wall instead of being held by it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from BreastBiomechLib.discrepancy.effects.base import Effect, EffectParameter
from BreastBiomechLib.discrepancy.variants import Variant

REFERENCE_STIFFNESS = 340.0  # Pa/mm: about fat's shear modulus over a 10 mm layer


class ChestWallSliding(Effect):
    """The chest wall's nodes held along the local chest-surface normal only, free along it but
    for tangential springs of k_ref (1 - s) / s Pa/mm (:func:`~BreastBiomechLib.solver.supports.chest_wall_support`,
    k_ref = :data:`REFERENCE_STIFFNESS`): s = 0 is the fit's chest wall (held
    anterior-posteriorly, the seed's), s = 1 free sliding on the loose retromammary fascia. The
    field-of-view cut stays fixed and holds the model."""

    name = "chest-wall"
    title = "chest-wall sliding"
    acts_in = "the posterior band at the chest wall"
    own_model = True
    order = 2
    parameters = (EffectParameter("s", "", 0.0, 0.0, 1.0, 1.0, "sliding freedom on the chest wall (1: free)"),)

    def unavailable(self, fitted) -> str | None:
        if "chest_wall" not in fitted.mesh.point_data or not len(fitted.mesh.node_set("chest_wall")):
            return "the fitting mesh has no chest-wall node set"
        return None

    def apply(self, variant: Variant, values, fitted) -> Variant:
        from BreastBiomechLib.solver.supports import chest_wall_support

        s = float(np.clip(values[0], 0.0, 1.0))
        if s == 0.0:
            return variant
        mesh = variant.model.mesh
        chest = mesh.node_set("chest_wall")
        cut = mesh.node_set("fov_cut") if "fov_cut" in mesh.point_data else np.zeros(0, np.int64)
        held, supports, note = chest_wall_support(mesh, chest, "sliding",
                                                  tangential_stiffness=REFERENCE_STIFFNESS * (1.0 - s) / s,
                                                  anchor=not len(cut),
                                                  held_by="the fixed field-of-view cut" if len(cut) else "")
        loading = variant.model.loading
        others = [c for c in loading.constraints if not np.array_equal(np.unique(c.nodes), np.unique(chest))]
        loading = replace(loading, constraints=others + held, supports=supports, notes=[note])
        return replace(variant, model=replace(variant.model, loading=loading))
