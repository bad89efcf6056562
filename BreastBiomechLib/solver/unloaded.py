"""The unloaded (stress-free) reference state of an imaged, gravity-loaded breast, and models that
start pre-stressed from it.

An MR image shows the breast deformed by gravity (prone: hanging anteriorly), yet a model meshed
from it takes that shape as stress-free. :func:`unloaded_shape` estimates the shape that, loaded
by the given gravity with the model's supports, comes to rest at the imaged one, by the backward
displacement iteration (Sellier 2011; Rajagopal et al. 2008; Eiben et al. 2016): X <- X - (x(X) -
x_imaged), where x(X) is the forward gravity-loaded equilibrium of a mesh with nodes X, solved
by dynamic relaxation. :func:`prestressed_model` then gives the model of a compression that
starts from the gravity-loaded equilibrium of that stress-free shape, with gravity on (or
changing to another posture's) while the plates close.

Positions in LPS mm, gravity in m/s^2 in the same frame (prone MR: anterior, LPS (0, -g, 0)).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.solver.model import Loading, Model, ReferenceState
from BreastBiomechLib.solver.settings import DynamicRelaxation
from BreastBiomechLib.solver.tled import solve


@dataclass
class UnloadedShape:
    """The estimated stress-free node positions ``nodes`` (N, 3) mm, the gravity-loaded
    equilibrium displacement from them ``loaded_displacement`` (N, 3) mm (nodes + it is within
    ``residual_mm`` of the imaged nodes), the ``gravity`` (m/s^2, LPS), the ``iterations`` taken,
    the largest node mismatch after each (``history``, mm) and the wall time (s)."""

    nodes: np.ndarray
    loaded_displacement: np.ndarray
    gravity: np.ndarray
    iterations: int
    residual_mm: float
    wall_time: float
    history: list[float] = field(default_factory=list)

    @property
    def largest_sag_mm(self) -> float:
        """The largest node displacement (mm) from the stress-free to the imaged shape."""
        return float(np.linalg.norm(self.loaded_displacement, axis=1).max())


def _gravity_only(model: Model, nodes: np.ndarray, gravity: np.ndarray) -> Model:
    """``model``'s mesh moved to ``nodes``, with its constraints and supports and only gravity
    as load (no plates, no pre-stress)."""
    mesh = TetMesh(nodes, model.mesh.tets, dict(model.mesh.point_data), dict(model.mesh.cell_data))
    loading = replace(model.loading, plates=[], gravity=gravity)
    return replace(model, mesh=mesh, loading=loading, prestate=None)


def unloaded_shape(model: Model, gravity, tolerance_mm: float = 0.02, max_iterations: int = 30,
                   device=None, relaxation: DynamicRelaxation | None = None,
                   progress=None) -> UnloadedShape:
    """The stress-free shape of ``model``'s mesh taken as imaged under ``gravity`` (m/s^2, LPS),
    with the model's constraints, supports and materials (its plates are left out): iterate until
    the forward gravity-loaded equilibrium of the estimate reproduces the imaged nodes within
    ``tolerance_mm`` (largest node distance). ``progress(iteration, residual_mm)`` is called
    after each forward solve. Raises a ValueError naming the problem when a forward solve fails
    (e.g. an element inverts: gravity too large for the supports or materials) or the iteration
    stops converging."""
    gravity = np.asarray(gravity, float).reshape(3)
    if not np.all(np.isfinite(gravity)):
        raise ValueError(f"gravity must be three finite numbers (m/s^2, LPS), not {gravity.tolist()}")
    if not tolerance_mm > 0 or max_iterations < 1:
        raise ValueError("the unloaded-shape iteration needs tolerance_mm > 0 and max_iterations >= 1")
    if not model.loading.constraints and not model.loading.supports:
        raise ValueError("the model has no constraints or supports: under gravity it would fall; fix the chest wall")
    relaxation = relaxation or DynamicRelaxation(tolerance_mm=min(0.01, tolerance_mm / 4))
    imaged = np.asarray(model.mesh.nodes, float)
    estimate = imaged.copy()
    history: list[float] = []
    started = time.perf_counter()
    for iteration in range(1, max_iterations + 1):
        forward = solve(_gravity_only(model, estimate, gravity), device=device, relaxation=relaxation)
        if not forward.ok:
            raise ValueError(f"unloaded shape, iteration {iteration}: the gravity-loaded solve of the estimate "
                             f"failed ({forward.status}: {forward.message})")
        mismatch = estimate + forward.displacement - imaged
        residual = float(np.linalg.norm(mismatch, axis=1).max())
        history.append(residual)
        if progress is not None:
            progress(iteration, residual)
        if residual <= tolerance_mm:
            return UnloadedShape(estimate, forward.displacement, gravity, iteration, residual,
                                 time.perf_counter() - started, history)
        if len(history) >= 4 and residual > 0.9 * history[-4]:
            raise ValueError(f"the unloaded-shape iteration stopped converging at {residual:.3g} mm after {iteration} "
                             f"iterations (residuals {', '.join(f'{r:.3g}' for r in history[-4:])} mm); the tissue may "
                             "be too soft for this gravity, or the supports too weak")
        estimate = estimate - mismatch
    raise ValueError(f"the unloaded shape did not reach {tolerance_mm} mm in {max_iterations} iterations (last "
                     f"{history[-1]:.3g} mm); raise max_iterations or the tolerance")


def prestressed_model(model: Model, unloaded: UnloadedShape, gravity=None) -> Model:
    """``model`` (meshed on the imaged shape, with its plates placed against it) starting
    pre-stressed: its mesh the ``unloaded`` stress-free shape, the tissue at rest at the start in
    the gravity-loaded equilibrium (within the unloaded shape's residual of the imaged nodes),
    gravity on from the start and, over the loading, ``gravity`` (m/s^2, LPS; None: unchanged,
    the imaged posture's). Plates that would start inside the tissue by up to that residual are
    moved back onto it, ending where they did."""
    if len(unloaded.nodes) != len(model.mesh.nodes):
        raise ValueError(f"the unloaded shape has {len(unloaded.nodes)} nodes, the model {len(model.mesh.nodes)}")
    final_gravity = unloaded.gravity if gravity is None else np.asarray(gravity, float).reshape(3)
    start = unloaded.nodes + unloaded.loaded_displacement
    plates = []
    for plate in model.loading.plates:
        gaps = plate.gaps(start[plate.slave_nodes])
        back = max(0.0, -float(gaps[np.isfinite(gaps)].min(initial=0.0)))
        plates.append(replace(plate, point=plate.point - back * plate.normal,
                              displacement=plate.displacement + back * plate.normal))
    mesh = TetMesh(unloaded.nodes, model.mesh.tets, dict(model.mesh.point_data), dict(model.mesh.cell_data))
    loading: Loading = replace(model.loading, plates=plates, gravity=final_gravity)
    return replace(model, mesh=mesh, loading=loading,
                   prestate=ReferenceState(unloaded.loaded_displacement, unloaded.gravity))


def start_from_reference_state(model: Model, request, device=None, progress=None,
                               relaxation: DynamicRelaxation | None = None) -> tuple[Model, dict]:
    """A case's ``reference_state`` (:class:`BreastBiomechLib.solver.settings.UnloadedRequest`) applied:
    ``model``'s mesh taken as imaged under ``request.imaged_gravity``, its unloaded shape
    estimated, and the pre-stressed model with the model's gravity over the loading. Returns
    the model and the figures to report (imaged gravity, iterations, residual and largest sag in
    mm, wall time in s); ``relaxation``: the forward solves' settings (None: the defaults). Part of
    :func:`~BreastBiomechLib.solver.run_case.run_case`."""
    unloaded = unloaded_shape(model, request.imaged_gravity, request.tolerance_mm, request.max_iterations,
                              device=device, relaxation=relaxation, progress=progress)
    figures = {"imaged_gravity": np.asarray(request.imaged_gravity, float).tolist(),
               "iterations": unloaded.iterations, "residual_mm": unloaded.residual_mm,
               "wall_s": unloaded.wall_time, "largest_sag_mm": unloaded.largest_sag_mm}
    return prestressed_model(model, unloaded, model.loading.gravity), figures


def displacement_from_imaged(model: Model, displacement: np.ndarray, imaged_nodes: np.ndarray) -> np.ndarray:
    """A solve's ``displacement`` (N, 3) mm of ``model`` as displacement from the mesh as imaged
    (``imaged_nodes``, LPS mm): for a pre-stressed model, whose mesh is the unloaded shape, its
    final positions minus the imaged nodes; otherwise the displacement as it is."""
    if model.prestate is None:
        return displacement
    return model.mesh.nodes + displacement - np.asarray(imaged_nodes, float)
