"""Absolute moduli from a measured plate force.

With the plates' travel prescribed, the chest wall held and no gravity in the fit's model, the
static equilibrium depends only on the ratios of the moduli: scaling every stiffness (each
tissue's E and the anisotropic fibre stiffness eta) by s leaves the displacement - and so the
predicted image and landmarks a fit compares - unchanged, and scales every force by s (Coulomb
friction included: it bounds a ratio of forces). A fit therefore finds ratios, with fat's E held
at its reference (:data:`~BreastBiomechLib.optimisation.space.REFERENCE_E`); a plate force measured
in one or more states (``force.json``: :class:`~BreastBiomechLib.io.case_layout.PlateForce`)
fixes the scale. For each such state the fitted model's normal force on the plate named (both
plates' mean where none is) is the prediction P_i; the scale is the weighted least-squares
s = sum(F_i P_i / sd_i^2) / sum(P_i^2 / sd_i^2) with sd(s) = 1 / sqrt(sum(P_i^2 / sd_i^2)): the
measurement's uncertainty only (the prediction's own error - the mesh, the model - is not in it).

Units: N, Pa; the scale is dimensionless.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from BreastBiomechLib.io.case_layout import PlateForce

STIFFNESSES = ("E", "eta")  # the material parameters that scale with the forces (Pa); nu does not


@dataclass
class ForceScale:
    """The scale ``scale`` (sd ``sd``) that turns the fit's moduli into absolute ones, and per
    state its record: {"measured_N", "sd_N", "plate", "predicted_N"} (the prediction at the fit's
    moduli, before scaling)."""

    scale: float
    sd: float
    states: dict = field(default_factory=dict)

    def materials(self, materials: dict) -> dict:
        """``materials`` ({tissue: {"E", "nu", "eta"}}) with every stiffness times the scale."""
        return {tissue: {k: v * self.scale if k in STIFFNESSES else v for k, v in values.items()}
                for tissue, values in materials.items()}

    def to_dict(self, materials: dict | None = None) -> dict:
        out = {"scale": self.scale, "sd": self.sd, "states": self.states}
        if materials is not None:
            out["materials"] = self.materials(materials)
        return out


def not_scale_free(model) -> str:
    """Why forces measured on ``model`` would not fix a single scale ("" where they do): gravity
    in its loading, or elastic surface supports (springs of a stiffness of their own)."""
    loading = model.loading
    if np.any(np.asarray(loading.gravity, float) != 0.0):
        return "the fit's model holds gravity, whose body force does not scale with the moduli"
    if any(s.normal_stiffness != 0.0 or s.tangential_stiffness != 0.0 for s in loading.supports):
        return "the fit's model holds elastic supports, whose springs do not scale with the moduli"
    return ""


def predicted_force(solution, plates, plate: str | None) -> float:
    """The normal force (N) of ``solution`` on the plate named ``plate`` of ``plates`` (the
    model's :class:`~BreastBiomechLib.solver.model.Plate` list, in the solution's order), or with
    None the mean over the plates. A ValueError names an unknown plate."""
    forces = np.asarray(solution.plate_normal_forces, float)
    if plate is None:
        return float(forces.mean())
    names = [p.name for p in plates]
    if plate not in names:
        raise ValueError(f"the measured force is on plate {plate!r}; the fit's plates are {', '.join(names)}")
    return float(forces[names.index(plate)])


def force_scale(records: dict[str, tuple[PlateForce, float]]) -> ForceScale:
    """The scale from each state's measured force and its prediction at the fit's moduli
    (``records``: state name -> (:class:`PlateForce`, predicted N)). A ValueError where a
    prediction is not a positive force (the plate does not press on the tissue in the model)."""
    if not records:
        raise ValueError("no measured plate force to scale the moduli by")
    weight = numerator = 0.0
    states = {}
    for name, (measured, predicted) in records.items():
        if not (np.isfinite(predicted) and predicted > 0):
            raise ValueError(f"state {name!r}: the fitted model's plate force is {predicted:.3g} N, no press on the "
                             "tissue to scale by")
        weight += predicted ** 2 / measured.sd ** 2
        numerator += measured.newtons * predicted / measured.sd ** 2
        states[name] = {"measured_N": measured.newtons, "sd_N": measured.sd, "plate": measured.plate,
                        "predicted_N": predicted}
    return ForceScale(numerator / weight, 1.0 / np.sqrt(weight), states)
