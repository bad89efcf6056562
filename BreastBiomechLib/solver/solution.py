"""The result of one solve (:class:`Solution`): displacements, plate forces, status and the
sampled energy history."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Solution:
    """Result of one solve. Displacements in mm (LPS), forces in N, energies in J, times in s.

    ``plate_forces[p]`` is the force plate p applies to the tissue (its normal and tangential -
    friction - parts: ``plate_normal_forces``, ``plate_tangential_forces``); ``history`` holds sampled
    ``time``, ``kinetic``, ``internal`` (energies), ``plate_forces`` (samples, P, 3) and
    ``stable_time_step`` (the power-iteration bound for the deformed model, see
    :mod:`BreastBiomechLib.solver.stability`). With visco materials ``internal`` is the stored
    hyperelastic energy at the instantaneous moduli (the dissipated energy is not tracked)."""

    displacement: np.ndarray
    plate_forces: np.ndarray
    status: str
    message: str
    steps: int
    time_step: float
    wall_time: float
    ke_ie_at_end_of_loading: float
    history: dict = field(default_factory=dict)
    estimated_error_mm: float = float("nan")  # dynamic relaxation: distance to the static solution
    stable_time_step: float = float("inf")  # last power-iteration estimate for the deformed model (s)
    plate_normals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (P, 3) towards the tissue
    attempts: int = 1  # solves it took: more where :mod:`~BreastBiomechLib.solver.retries` slowed the load
    # dynamic relaxation: the lowest eigenvalue of M^-1 K it found (1/s^2, the least Rayleigh quotient
    # after the load) and the volume-weighted mean mu / rho of its fictitious masses (m^2/s^2) that
    # the eigenvalue scales with; a warm start from this solve carries both (NaN: not a relaxation)
    lowest_eigenvalue: float = float("nan")
    shear_speed_squared: float = float("nan")

    @property
    def plate_normal_forces(self) -> np.ndarray:
        """(P,) the normal part of each plate's force (N, > 0 pressing on the tissue)."""
        return np.einsum("pi,pi->p", self.plate_forces, self.plate_normals)

    @property
    def plate_tangential_forces(self) -> np.ndarray:
        """(P, 3) the tangential part of each plate's force (N, LPS): friction (zero without)."""
        return self.plate_forces - self.plate_normal_forces[:, None] * self.plate_normals

    @property
    def ok(self) -> bool:
        return self.status == "completed"
