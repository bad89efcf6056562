"""Gravity: the imaged breast is loaded by its weight, and the compression starts from that
pre-stressed state rather than from a stress-free one."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from BreastBiomechLib.discrepancy.effects.base import Effect, EffectParameter
from BreastBiomechLib.discrepancy.variants import Variant

STANDARD_GRAVITY = 9.81  # m/s^2
KEPT_SHAPES = 4  # unloaded shapes kept for variants that share one


class GravityPrestress(Effect):
    """The compression solved from the breast's gravity-loaded state: its stress-free shape
    estimated from the imaged one (:func:`~BreastBiomechLib.solver.unloaded.unloaded_shape`)
    under s x 9.81 m/s^2 along the undeformed scan's posture (the fit's ``imaged_gravity``;
    prone MR: anterior), then gravity along the compressed scan's posture (``compressed_gravity``,
    recorded with the case: the same posture, or another one, e.g. upright for a mammogram) while
    the plates close. The moduli are scaled to fat's 10 kPa reference, which the plates'
    prescribed motion cannot see but gravity can: s is therefore also 10 kPa / E_fat, and s = 2
    means a breast half as stiff as the reference."""

    name = "gravity"
    title = "gravity pre-stress (unloaded state)"
    acts_in = "the whole breast, most where it hangs furthest from the chest wall"
    own_model = True
    order = 9
    parameters = (EffectParameter("s", "x 9.81 m/s^2", 0.0, 0.0, 3.0, 1.0,
                                  "gravity, or fat's 10 kPa over its real modulus"),)

    def __init__(self):
        # the unloaded shapes last estimated ({(id of the model, s, materials' digest): (model, shape)}):
        # variants that differ from another only in what happens while the plates close (another
        # plate pose, gravity turned at the compressed scan) start from the same shape
        self._shapes: dict = {}

    def unavailable(self, fitted) -> str | None:
        if not np.any(fitted.imaged_gravity) or not np.any(fitted.compressed_gravity):
            return "the scans' postures (gravity) are not known"
        return None

    def apply(self, variant: Variant, values, fitted) -> Variant:
        from BreastBiomechLib.solver.unloaded import prestressed_model, unloaded_shape

        s = float(values[0])
        if s <= 0.0:
            return variant
        imaged = s * STANDARD_GRAVITY * _unit(fitted.imaged_gravity)
        model = replace(variant.model, materials=variant.materials,
                        loading=replace(variant.model.loading, plates=variant.plates))
        key = (id(variant.model), s, _digest(variant.materials))
        unloaded = self._shapes.get(key)
        if unloaded is None or unloaded[0] is not variant.model:
            shape = unloaded_shape(model, imaged, tolerance_mm=0.05, device=fitted.device, relaxation=fitted.relaxation)
            unloaded = self._shapes[key] = (variant.model, shape)
            while len(self._shapes) > KEPT_SHAPES:
                self._shapes.pop(next(iter(self._shapes)))
        compressed = fitted.compressed_gravity if variant.compressed_gravity is None else variant.compressed_gravity
        loaded = prestressed_model(model, unloaded[1], s * STANDARD_GRAVITY * _unit(compressed))
        return Variant(loaded, variant.materials, loaded.loading.plates)


def _digest(materials) -> str:
    """A digest of per-element ``materials`` (what the unloaded shape depends on besides the mesh,
    its supports and gravity)."""
    import hashlib

    h = hashlib.blake2b(digest_size=16)
    for name in ("mu", "kappa", "eta", "fibre", "density"):
        h.update(np.ascontiguousarray(getattr(materials, name)).tobytes())
    return h.hexdigest()


def _unit(gravity) -> np.ndarray:
    gravity = np.asarray(gravity, float)
    return gravity / np.linalg.norm(gravity)
