"""How a model is solved: :class:`DynamicRelaxation` (the fast path to the static solution), a
case's :class:`UnloadedRequest` (start pre-stressed from the imaged shape's unloaded state) and
:class:`SolverSettings`, the choice of method, device and their options that every way of running
a case takes (:func:`BreastBiomechLib.solver.run_case.run_case`, case files, the Simulation panel).

Units: mm for distances, s for times, m/s^2 for gravity (LPS). Light: numpy only (no warp), so that
case files and panels can hold settings before the solver is imported.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

MM = 1e-3  # metres per millimetre
FRICTION_WAVE_CROSSINGS = 6.0  # relaxation with friction loads over this many shear-wave crossings


@dataclass
class DynamicRelaxation:
    """Fast path to the static solution (Joldes, Wittek & Miller): element densities scaled so
    every element has the same stable step (mass scaling), the load applied over
    ``load_iterations`` steps, then damping set every ``update_every`` steps to twice the square
    root of the lowest eigenvalue of M^-1 K, estimated by Rayleigh quotients of the displacement
    change since a reference state renewed every :data:`relaxation.QUOTIENT_WINDOW` updates. For
    :data:`relaxation.SETTLING_UPDATES` updates after a cold load the damping follows the latest quotient
    (the load's transient, whose fast modes it damps); after that the least quotient since sets
    it: every quotient bounds the lowest eigenvalue from above, so the damping only falls, towards
    the lowest mode's critical value, as slower modes show in the motion (following the latest
    quotient instead overdamps the slow modes near rest, whose creep reads as converged).
    Where the kinetic energy has grown :data:`relaxation.SURGE` times since the previous update - energy
    released after the load: a snap to another configuration, contact chatter - the damping
    follows the latest quotient for another :data:`relaxation.SETTLING_UPDATES` updates (under the least
    quotient's damping such a motion grew until an element of a coarse fitting mesh inverted).
    Where the motion has not contracted at :data:`relaxation.CHATTER_UPDATES` updates in a row and the
    quotient is over :data:`relaxation.CHATTER_QUOTIENT` times the least, it is high-frequency chatter -
    contact, stiffening fibres - that the lowest mode's damping cannot remove, and the damping
    follows the quotient up. Each model stops when the estimated distance to the static solution
    (:class:`DistanceToRest`, from the displacement change between updates) is below
    ``tolerance_mm`` at two updates in a row at which its motion is not slowing down. A change
    below the model's float32 noise floor (:func:`stress_noise_floor_mm`) whose quotient is over
    :data:`relaxation.CHATTER_QUOTIENT` times the least is rounding noise about rest, counted as rest at that
    distance (nearly incompressible tissue wanders by up to 1e-3 mm at rest, with contraction
    ratios jumping above and below 1 that the estimate cannot extrapolate).

    A warm start (:mod:`BreastBiomechLib.solver.warm`) caps the damping at its start's lowest
    mode, so its approach is never overdamped: its damping follows the latest quotient (over one
    update interval) under that cap, and it stops where the estimate is below the tolerance at two
    updates in a row, three updates after its plates' ramp at the earliest. Time in a relaxation
    run is fictitious.

    The decisions at each update are made on the device (:mod:`BreastBiomechLib.solver.relaxation`),
    so the next steps run while the host reads the update's figures.

    ``load_iterations`` is a minimum: the load is applied slowly enough that prescribed boundaries
    (plates, displacements) move at under a third of the shear wave speed of the scaled model,
    which for near-incompressible tissue (c_dilatational / c_shear = 7 at nu = 0.49, 22 at 0.499)
    can take more iterations; faster loading crushes the surface elements. In a batch each model
    loads as slowly as its own materials and travel need (and its damping adapts and its
    convergence counts from the end of its own load), so a stiff-bulk model does not slow the
    others down. ``pace`` (>= 1) stretches each model's load that many times further (the retry of
    a model that inverted an element on the way, :mod:`BreastBiomechLib.solver.retries`)."""

    load_iterations: int = 1000
    tolerance_mm: float = 0.01
    max_iterations: int = 50_000
    update_every: int = 200
    pace: float = 1.0

    def load_iterations_for(self, travel_mm: float, wave_speed_ratio: float, length_m: float, safety: float,
                            friction_extent_m: float = 0.0) -> int:
        """Iterations to apply a load whose prescribed boundaries move up to ``travel_mm``: at
        least ``load_iterations``, and enough that the fastest motion (the 3-4-5 ramp peaks at
        1.875x its mean speed) stays below a third of the slowest shear wave, which crosses an
        element of altitude ``length_m`` in (c_d / c_s) / safety steps under mass scaling.

        With plate friction (``friction_extent_m`` > 0, the model's largest extent) the answer
        depends on the path, so the load must follow the plates' monotone path quasi-statically
        as physical time does: it lasts at least :data:`FRICTION_WAVE_CROSSINGS` times the time a
        shear wave takes to cross the model, longer than its slowest modes' periods, so contact
        nodes do not overshoot and stick where a slow load would not have put them (a 10 mm TetGen
        breast at mu = 0.3 loaded over 300 iterations ended 0.35 mm from the physical-time
        solution; over 3, 4, 6 and 10 crossings 0.084, 0.036, 0.016 and 0.023 mm). All of it
        times ``pace``."""
        needed = 3.0 * 1.875 * travel_mm * MM * wave_speed_ratio / (safety * length_m)
        crossing = FRICTION_WAVE_CROSSINGS * friction_extent_m * wave_speed_ratio / (safety * length_m)
        return int(math.ceil(self.pace * max(self.load_iterations, needed, crossing)))

    def __post_init__(self) -> None:
        if self.load_iterations < 2 or self.max_iterations <= self.load_iterations:
            raise ValueError("dynamic relaxation needs load_iterations >= 2 and max_iterations > load_iterations")
        if self.tolerance_mm <= 0 or self.update_every < 10:
            raise ValueError("dynamic relaxation needs tolerance_mm > 0 and update_every >= 10")
        if not self.pace >= 1.0:
            raise ValueError(f"dynamic relaxation's pace must be >= 1 (a load that many times slower), not {self.pace}")


SOLVER_METHODS = ("relaxation", "physical", "static")


@dataclass
class UnloadedRequest:
    """A case's ``reference_state``: the mesh is the shape imaged under ``imaged_gravity`` (m/s^2,
    LPS; prone MR: anterior, (0, -9.81, 0)); the solve starts pre-stressed from its estimated
    stress-free shape (:mod:`BreastBiomechLib.solver.unloaded`, to ``tolerance_mm`` within
    ``max_iterations``), with the case's ``gravity`` acting over the loading."""

    imaged_gravity: np.ndarray
    tolerance_mm: float = 0.02
    max_iterations: int = 30

    def __post_init__(self) -> None:
        self.imaged_gravity = np.asarray(self.imaged_gravity, float).reshape(3)
        if not np.all(np.isfinite(self.imaged_gravity)):
            raise ValueError(f"imaged_gravity must be three finite numbers (m/s^2, LPS), not "
                             f"{self.imaged_gravity.tolist()}")
        if not self.tolerance_mm > 0 or int(self.max_iterations) < 1:
            raise ValueError("the reference state needs tolerance_mm > 0 and max_iterations >= 1")


@dataclass
class SolverSettings:
    """How to solve a case: ``method`` "relaxation" (static solution, fast), "physical"
    (explicit dynamics in physical time) or "static" (the Newton reference of
    :mod:`BreastBiomechLib.solver.static`: CPU, float64, small models), the device ("cuda",
    "cpu", or None for warp's default), the dynamic-relaxation settings, for physical time the
    optional early stop at steady state and mass scaling, and for static the number of load
    increments."""

    method: str = "relaxation"
    device: str | None = None
    relaxation: DynamicRelaxation = field(default_factory=DynamicRelaxation)
    steady_state_mm: float | None = None  # physical time: stop settling once this close to rest
    increments: int | None = None  # static: load steps (None: the solver's default)
    mass_scaling: bool = False  # physical time: scale element masses up to a common stable step
    unloaded: UnloadedRequest | None = None  # start pre-stressed from the imaged shape's unloaded state

    def __post_init__(self) -> None:
        if self.method not in SOLVER_METHODS:
            raise ValueError(f"solver method must be one of {SOLVER_METHODS}, not {self.method!r}")
        if self.steady_state_mm is not None and self.method != "physical":
            raise ValueError("steady_state_mm applies to the physical method; relaxation has tolerance_mm")
        if self.increments is not None and self.method != "static":
            raise ValueError("increments apply to the static method")
        if self.mass_scaling and self.method != "physical":
            raise ValueError("mass_scaling applies to the physical method (relaxation always scales masses)")
