"""Warm starts of dynamic relaxation: a solve that begins at the equilibrium of a nearby problem.

In a fit the models solved one after another share the mesh, the constraints and the plates' poses
and differ in materials and plate travel only. The relaxation of a cold solve applies the load
slowly (so the surface is not crushed) and then relaxes from a configuration tens of millimetres
from rest; started at a nearby parameter set's equilibrium it applies the constraints and gravity
at once (the start satisfies them already), moves the plates only by the difference in travel, and
relaxes from a configuration a fraction of a millimetre from rest. Static equilibrium of a
hyperelastic model in frictionless contact does not depend on the path, so the solution is the
cold solve's, within the relaxation's tolerance; with friction it does, so friction refuses a
warm start.

The damping matters more than the start. The relaxation sets it from the Rayleigh quotient of the
displacement change, which after a cold load measures the lowest mode; after a warm start the
change is the start's local misfit (mostly high modes, concentrated where the plates and the chest
wall hold the tissue), whose quotient is ten to a thousand times the lowest eigenvalue: damped
that much, the approach creeps and the distance-to-rest estimate reads the creep as convergence
(0.1 mm from rest against a 0.01 mm tolerance, on the 20k-tet benchmark breast with mu x 0.3).
So a warm start carries the lowest eigenvalue its start's solve found, scaled to the new materials
by the mean mu / rho of the fictitious masses, and the damping never exceeds
:data:`DAMPING_MARGIN` times its critical value.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from BreastBiomechLib.solver.model import Model, Plate

DAMPING_MARGIN = 0.85  # of the carried critical damping: below it is slower but safe, above it is not
ITERATIONS_FACTOR = 2.0  # a warm start that has not converged in this many times its start's iterations stops


@dataclass
class WarmStart:
    """Where a relaxation starts: ``displacement`` (N, 3) mm, an equilibrium of the same model
    (mesh, constraints, gravity and plate poses) with other materials, reached with the plates'
    travel ``plate_displacements`` (P, 3) mm (None: the model's own plates' travel);
    ``lowest_eigenvalue`` (1/s^2) and ``shear_speed_squared`` (m^2/s^2): that solve's
    :class:`~BreastBiomechLib.solver.Solution` figures (NaN: unknown, the damping then adapts
    as after a cold load, slower and less safely); ``iterations``: the most a solve on the way to
    it took (the cold solve it began from, or a warm one that took more; None: unknown), which
    bound a warm start's own (:meth:`bounded`). Made by :meth:`from_solution`."""

    displacement: np.ndarray
    plate_displacements: np.ndarray | None = None
    lowest_eigenvalue: float = float("nan")
    shear_speed_squared: float = float("nan")
    iterations: int | None = None

    @classmethod
    def from_solution(cls, solution, plate_displacements: np.ndarray | None = None,
                      started: "WarmStart | None" = None) -> "WarmStart":
        """The warm start at a completed relaxation ``solution`` reached with the plates' travel
        ``plate_displacements`` (P, 3) mm (None: the model's own); ``started``: the warm start
        that solution began from, if any (its :attr:`iterations` carried where larger: a warm
        solve takes fewer than a cold one, and a chain of warm starts must not tighten the
        bound)."""
        if not solution.ok:
            raise ValueError(f"a warm start needs a completed solve, not one that ended {solution.status!r}")
        before = started.iterations if started is not None and started.iterations is not None else 0
        return cls(solution.displacement, plate_displacements, solution.lowest_eigenvalue,
                   solution.shear_speed_squared, max(int(solution.steps), int(before)))

    def bounded(self, relaxation):
        """``relaxation`` (a :class:`~BreastBiomechLib.solver.settings.DynamicRelaxation`) with
        its iterations bounded by :data:`ITERATIONS_FACTOR` times the start's: a warm start that
        has not converged by then has met what it cannot do quickly (on a diagnosis's 12 mm mesh,
        a plate pushed 1 mm further than its start's set a contact oscillating that the start's
        damping did not settle in 50 000 iterations, where a cold solve took 2 800) and ends "not
        converged", for the caller to solve it cold. Unchanged where the start's iterations are
        unknown."""
        if self.iterations is None:
            return relaxation
        bound = max(int(np.ceil(ITERATIONS_FACTOR * self.iterations)), relaxation.load_iterations + 1)
        return replace(relaxation, max_iterations=min(relaxation.max_iterations, bound))

    def critical_damping(self, shear_speed_squared: np.ndarray) -> np.ndarray:
        """(B,) the damping (1/s) the warm start allows models whose mean mu / rho is
        ``shear_speed_squared`` (m^2/s^2): :data:`DAMPING_MARGIN` times twice the square root of
        the start's lowest eigenvalue scaled by their ratio to the start's."""
        ratio = np.asarray(shear_speed_squared, float) / self.shear_speed_squared
        return DAMPING_MARGIN * 2.0 * np.sqrt(self.lowest_eigenvalue * ratio)

    def __post_init__(self) -> None:
        self.displacement = np.asarray(self.displacement, float)
        if self.displacement.ndim != 2 or self.displacement.shape[1] != 3:
            raise ValueError(f"a warm start's displacement is (N, 3) mm, not {self.displacement.shape}")
        if not np.isfinite(self.displacement).all():
            raise ValueError("a warm start's displacement has non-finite values: start from a completed solve")
        if self.plate_displacements is not None:
            self.plate_displacements = np.asarray(self.plate_displacements, float).reshape(-1, 3)


def started_plates(model: Model, warm: WarmStart, plate_sets: list[list[Plate]]) -> list[list[Plate]]:
    """Each model's plates as a warm start moves them: from where ``warm``'s plates ended to
    where the model's end, i.e. the same plates with ``point`` advanced by the start's travel
    and ``displacement`` the difference. Raises ValueError where a warm start does not apply:
    another number of nodes, plates with friction (the equilibrium depends on the path), plates
    whose pose or edge differs from the model's (only travel may)."""
    own = model.loading.plates
    n_nodes = len(model.mesh.nodes)
    if warm.displacement.shape[0] != n_nodes:
        raise ValueError(f"the warm start has {warm.displacement.shape[0]} nodes, the model {n_nodes}: start from "
                         "a solve of the same mesh")
    start = (np.array([p.displacement for p in own]).reshape(-1, 3) if warm.plate_displacements is None
             else warm.plate_displacements)
    if start.shape[0] != len(own):
        raise ValueError(f"the warm start's plate travel has {start.shape[0]} plates, the model {len(own)}")
    moved = []
    for plates in plate_sets:
        refusal = plates_refusal(model, plates)
        if refusal:
            raise ValueError(refusal)
        moved.append([replace(p, point=p.point + travel, displacement=p.displacement - travel)
                      for p, travel in zip(plates, start)])
    return moved


def plates_refusal(model: Model, plates: list[Plate]) -> str | None:
    """Why a variant of ``model`` with ``plates`` cannot start from another solve of it (plate
    friction, another pose or edge than the model's plates), or None where it may."""
    for p, o in zip(plates, model.loading.plates):
        if p.friction > 0:
            return (f"plate {p.name!r} has friction {p.friction}: its equilibrium depends on the loading "
                    "path, so it cannot start from another solve's; solve it cold")
        if not (np.allclose(p.point, o.point) and np.allclose(p.normal, o.normal) and _same_edge(p.edge, o.edge)):
            return (f"plate {p.name!r} has another pose or edge than the model's: a warm start may only "
                    "change the plates' travel")
    return None


def _same_edge(a, b) -> bool:
    if a is None or b is None:
        return a is b
    return np.allclose(a.direction, b.direction) and a.distance == b.distance and a.radius == b.radius


def ramp_iterations(relaxation, plate_sets: list[list[Plate]], wave_speed_ratios: np.ndarray, length_m: float,
                    safety: float) -> np.ndarray:
    """(B,) iterations over which a warm start moves each model's plates by their remaining
    travel (``plate_sets`` from :func:`started_plates`): as fast as the cold load's speed limit
    allows (:meth:`DynamicRelaxation.load_iterations_for` without its minimum); 0 where they do
    not move. ``wave_speed_ratios`` (B,): each model's c_dilatational / c_shear; ``length_m``:
    the median element altitude (m)."""
    fastest = replace(relaxation, load_iterations=2)
    iterations = []
    for plates, ratio in zip(plate_sets, wave_speed_ratios):
        travel = max([float(np.abs(p.displacement).max()) for p in plates], default=0.0)
        iterations.append(fastest.load_iterations_for(travel, float(ratio), length_m, safety) if travel > 0 else 0)
    return np.array(iterations)


def start_time(iterations: np.ndarray, dt: float) -> np.ndarray:
    """(B,) the load's duration (s) for ``iterations`` per model; 0 iterations (nothing to move)
    is half a step, so the load factor is 1 from the first step."""
    return np.where(iterations > 0, iterations * dt, 0.5 * dt)

