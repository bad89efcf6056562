"""The compressed scan's posture known only nominally: gravity at the compression turned from the
direction the case records."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from BreastBiomechLib.discrepancy.effects.base import Effect, EffectParameter, switched_on
from BreastBiomechLib.discrepancy.variants import Variant


class GravityDirection(Effect):
    """Gravity while the plates close turned from the compressed scan's recorded posture by two
    angles (degrees) about two axes perpendicular to it (:func:`turn_axes`): a woman standing at a
    mammography unit leans into it, one lying prone on a biopsy table is rolled a little, and a
    case records the posture by name (upright, prone), not its angle to a degree.

    It refines the gravity pre-stress: with no gravity in the model a turn of it changes nothing,
    so it is a candidate only once the gravity candidate was added in an earlier round (its
    secant models then reuse that model's unloaded shape: the turn acts while the plates close,
    not in the scan the shape is estimated from). Applied before the gravity pre-stress, which
    loads with the turned direction (``order``)."""

    name = "gravity-direction"
    title = "gravity's direction at the compressed scan"
    acts_in = "the whole breast, as it hangs in the compressed scan's posture"
    own_model = True
    order = 8
    parameters = tuple(EffectParameter(f"turn{a + 1}", "deg", 0.0, -30.0, 30.0, 10.0,
                                       f"gravity turned about its axis {a + 1} from the recorded posture")
                       for a in range(2))

    def unavailable(self, fitted) -> str | None:
        return self.unavailable_at(fitted, {})

    def unavailable_at(self, fitted, added) -> str | None:
        if not np.any(fitted.imaged_gravity) or not np.any(fitted.compressed_gravity):
            return "the scans' postures (gravity) are not known"
        if switched_on(added, "gravity"):
            return None
        return "the model has no gravity pre-stress yet: the gravity candidate comes first"

    def apply(self, variant: Variant, values, fitted) -> Variant:
        values = np.asarray(values, float)
        if not np.any(values):
            return variant
        return replace(variant, compressed_gravity=turned_gravity(fitted.compressed_gravity, values))


def turn_axes(gravity) -> np.ndarray:
    """(2, 3) unit axes perpendicular to ``gravity`` (LPS) about which :class:`GravityDirection`
    turns it: the first the cross product of gravity with the LPS axis it is least aligned with,
    the second completing a right-handed frame with gravity's direction."""
    g = np.asarray(gravity, float) / np.linalg.norm(gravity)
    first = np.cross(g, np.eye(3)[int(np.argmin(np.abs(g)))])
    first /= np.linalg.norm(first)
    return np.array([first, np.cross(g, first)])


def turned_gravity(gravity, angles_deg) -> np.ndarray:
    """``gravity`` (m/s^2, LPS) turned by ``angles_deg`` about its :func:`turn_axes` (as one
    rotation vector): the same magnitude, another direction."""
    rotation = Rotation.from_rotvec(np.radians(np.asarray(angles_deg, float)) @ turn_axes(gravity))
    return rotation.apply(np.asarray(gravity, float))
