"""One way to run a case: :func:`run_case` (one model) and :func:`run_variants` (variants of one
model in one batched launch), used by ``breastbiomech simulate``, the Breast Simulation module, the
phantom's truth solve and the discrepancy workflow's variants.

A run is: the reference state where the settings ask for one (the mesh taken as imaged under
gravity, its unloaded shape estimated and the model started pre-stressed from it,
:mod:`~BreastBiomechLib.solver.unloaded`); the solve by the settings' method (dynamic relaxation,
a variant that inverts an element solved again alone with a slower load,
:mod:`~BreastBiomechLib.solver.retries`; explicit dynamics in physical time; or the float64 static
reference); and the displacement from the mesh as imaged (not from the unloaded shape a
pre-stressed solve starts from). Displacements in mm (LPS), forces in N.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from BreastBiomechLib.solver.materials import ElementMaterials
from BreastBiomechLib.solver.model import Model, Plate
from BreastBiomechLib.solver.settings import SolverSettings
from BreastBiomechLib.solver.solution import Solution

KE_IE_LIMIT = 0.05  # physical time: the largest kinetic/internal energy ratio at the end of loading


@dataclass
class CaseVariant:
    """One variant of a model for :func:`run_variants`: its element ``materials`` and its
    ``plates`` (the model's own plates in number, order and contact nodes; pose, travel, edge and
    friction may differ). None: the model's own."""

    materials: ElementMaterials | None = None
    plates: list[Plate] | None = None


@dataclass
class CaseResult:
    """A case's run: the solver's ``solution`` of ``model`` (the model solved: pre-stressed from
    its unloaded shape where the settings asked for a reference state), ``displacement`` (N, 3) mm
    from the mesh as imaged (``imaged_nodes``), and the ``reference_state``'s figures (imaged
    gravity, iterations, residual and largest sag in mm, wall time in s) or None."""

    solution: Solution
    model: Model
    imaged_nodes: np.ndarray
    displacement: np.ndarray
    reference_state: dict | None = None

    @property
    def ok(self) -> bool:
        return self.solution.ok

    @property
    def unloaded_displacement(self) -> np.ndarray | None:
        """(N, 3) mm from the imaged mesh to the estimated unloaded shape, or None without one."""
        return None if self.reference_state is None else self.model.mesh.nodes - self.imaged_nodes


def run_case(model: Model, settings: SolverSettings | None = None,
             progress: Callable[[float], bool | None] | None = None,
             reference_progress: Callable[[int, float], None] | None = None,
             ke_ie_limit: float = KE_IE_LIMIT) -> CaseResult:
    """Run ``model`` with ``settings`` (default: dynamic relaxation on warp's default device).
    ``progress(fraction of the step budget)`` returning False cancels the solve (status
    "cancelled"); ``reference_progress(iteration, residual_mm)`` follows the unloaded-shape
    estimate; ``ke_ie_limit`` is physical time's energy criterion."""
    return run_variants(model, [CaseVariant()], settings, progress, reference_progress, ke_ie_limit)[0]


def run_variants(model: Model, variants: list[CaseVariant], settings: SolverSettings | None = None,
                 progress: Callable[[float], bool | None] | None = None,
                 reference_progress: Callable[[int, float], None] | None = None,
                 ke_ie_limit: float = KE_IE_LIMIT, imaged_nodes: np.ndarray | None = None,
                 warm_start=None) -> list[CaseResult]:
    """Run the ``variants`` of ``model`` with ``settings`` in one batched launch (the static
    method: one after the other); the results in the variants' order. ``imaged_nodes`` (N, 3) mm:
    the mesh as imaged, for a model pre-stressed already (its mesh the unloaded shape; default:
    the model's mesh). ``warm_start`` (dynamic relaxation only, no reference state): a
    :class:`~BreastBiomechLib.solver.warm.WarmStart` every variant starts at. See :func:`run_case`."""
    from BreastBiomechLib.solver.unloaded import displacement_from_imaged, start_from_reference_state

    settings = settings or SolverSettings()
    if not variants:
        raise ValueError("run_variants needs at least one variant")
    imaged = model.mesh.nodes if imaged_nodes is None else np.asarray(imaged_nodes, float)
    reference_state = None
    if warm_start is not None and (settings.method != "relaxation" or settings.unloaded is not None):
        raise ValueError("a warm start applies to dynamic relaxation of a model without a reference-state solve "
                         f"(method {settings.method!r}, unloaded state {'asked' if settings.unloaded else 'not asked'}): "
                         "solve it cold (warm_start=None), or use method='relaxation' without settings.unloaded")
    if settings.unloaded is not None:
        model, reference_state = start_from_reference_state(
            model, settings.unloaded, settings.device, progress=reference_progress,
            relaxation=settings.relaxation if settings.method == "relaxation" else None)
    materials = [model.materials if v.materials is None else v.materials for v in variants]
    plates = None if all(v.plates is None for v in variants) else [
        model.loading.plates if v.plates is None else v.plates for v in variants]
    solutions = _solve(model, materials, plates, settings, progress, ke_ie_limit, warm_start)
    return [CaseResult(s, model, imaged, displacement_from_imaged(model, s.displacement, imaged), reference_state)
            for s in solutions]


def _solve(model: Model, materials: list[ElementMaterials], plates: list[list[Plate]] | None,
           settings: SolverSettings, progress, ke_ie_limit: float, warm_start=None) -> list[Solution]:
    """The solutions of the variants by the settings' method."""
    if settings.method == "static":
        from BreastBiomechLib.solver.static import solve_static

        return [solve_static(replace(model, materials=m, loading=model.loading if plates is None
                                     else replace(model.loading, plates=plates[b])),
                             increments=settings.increments)
                for b, m in enumerate(materials)]
    if settings.method == "relaxation":
        from BreastBiomechLib.solver.retries import solve_batch_with_retries

        return solve_batch_with_retries(model, materials, settings.relaxation, plates=plates, device=settings.device,
                                        progress=progress, warm_start=warm_start)
    from BreastBiomechLib.solver.tled import solve_batch

    return solve_batch(model, materials, device=settings.device, plates=plates, progress=progress,
                       steady_state_mm=settings.steady_state_mm, mass_scaling=settings.mass_scaling,
                       ke_ie_limit=ke_ie_limit)
