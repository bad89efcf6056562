"""Total Lagrangian explicit dynamics (TLED) on NVIDIA warp: ``solve`` and ``solve_batch``.

Precomputed once: reference shape-function derivatives and volumes of the four-node tets, lumped
nodal masses, the critical time step. Each step: (ANP sums), element forces, then one
node kernel (``advance_nodes``, built by ``kernels.node_kernel``): the central difference update with mass-proportional
damping (seed eq. (15)) in increment form, with the displacement accumulated in float32 plus a
compensation term (Kahan summation), sliding supports, prescribed components, plate contact.
The step loop has no host synchronisation: on CUDA it replays captured graphs of ten steps (two
for the rest of an interval; graphs per count of moving models: the steps run only the models
still moving, see ``kernels``). Once half of a batch or more has stopped (converged, or an
inverted element), the batch is packed down to the models still moving (``packing``).
Every ``sample_every`` steps a second graph computes the energies, the stable-step estimate, the
plate forces and, in a relaxation, its decisions (damping, mass scaling, converged models: see
``relaxation``), and copies what the host reads back; a relaxation's next steps are enqueued before
the host reads it.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np
import warp as wp

from BreastBiomechLib.solver import cpu_pool
from BreastBiomechLib.solver import kernels as k
from BreastBiomechLib.solver.batch_run import BatchOptions, BatchRun
from BreastBiomechLib.solver.geometry import MeshGeometry
from BreastBiomechLib.solver.host_setup import (anp_mode, anp_partition_classes, anp_slots, constraint_load_shapes,
                                                material_table, merged_constraints)
from BreastBiomechLib.solver.materials import ElementMaterials
from BreastBiomechLib.solver.model import Model, Plate
from BreastBiomechLib.solver.ordering import SolverOrder
from BreastBiomechLib.solver.relaxation import MM
from BreastBiomechLib.solver.settings import DynamicRelaxation
from BreastBiomechLib.solver.solution import Solution
from BreastBiomechLib.solver.warm import WarmStart
from BreastBiomechLib.timing import staged


def _device(device):
    return wp.get_device(device) if device is not None else wp.get_device()


def internal_forces(model: Model, displacement_mm: np.ndarray, device=None) -> np.ndarray:
    """Internal nodal forces (N, 3) in newtons for a given displacement field (mm), with the
    model's formulation and its materials at equilibrium (visco terms fully relaxed): the residual
    the solver drives to the external load."""
    wp.init()
    geometry = MeshGeometry.of(model.mesh.nodes, model.mesh.tets)
    dhdx, vol = geometry.dhdx, geometry.vol
    N, M = len(model.mesh.nodes), len(model.mesh.tets)
    mat = model.materials.long_term()
    slots, slot_volume = anp_slots(model.mesh.tets, [mat], vol, model.anp_across_materials)
    f32 = np.float32
    with wp.ScopedDevice(_device(device)):
        u = wp.array(np.asarray(displacement_mm, f32) * f32(MM), dtype=wp.vec3)
        tets = wp.array(geometry.tets, dtype=int)
        d_dhdx = wp.array(dhdx.astype(f32), dtype=wp.vec3)
        d_vol = wp.array(vol.astype(f32), dtype=float)
        table = material_table([mat])
        anp_sums = wp.zeros(len(slot_volume), dtype=float)
        d_slots = wp.array(slots, dtype=int)
        forces = wp.zeros((3, N), dtype=float)  # component planes (see kernels)
        inverted = wp.zeros(4, dtype=int)
        anp = anp_mode(model)
        slots_are_nodes = bool(np.array_equal(slots, model.mesh.tets))
        one_model = wp.array([0], dtype=int)  # the list of models: model 0
        formulation = k.element_kernels(anp, False, slots_are_nodes)  # visco terms relaxed: none
        if anp != k.ANP_OFF:
            wp.launch(formulation.nodal_pressure, M,
                      [u, tets, d_slots, d_dhdx, d_vol, table, 1, one_model, 1, anp_sums])
        wp.launch(formulation.element_forces, M, [u, tets, d_dhdx, d_vol, table, d_slots, anp_sums,
                                                   wp.array(slot_volume.astype(f32), dtype=float), 0,
                                                   wp.zeros(1, dtype=float), wp.zeros(1, dtype=float),
                                                   wp.zeros(1, dtype=wp.mat33), 0, 1, wp.zeros(2, dtype=int),
                                                   one_model, 1, forces, inverted])
        if inverted.numpy()[0]:
            raise ValueError(f"element {inverted.numpy()[1]} is inverted (J <= 0) by this displacement")
        return forces.numpy().T.astype(np.float64, order="C")


def solve(model: Model, device=None, sample_every: int = 200, ke_ie_limit: float = 0.05,
          initial_displacement: np.ndarray | None = None, relaxation: DynamicRelaxation | None = None,
          progress: Callable[[float], bool | None] | None = None, steady_state_mm: float | None = None,
          mass_scaling: bool = False) -> Solution:
    """Solve one model; ``device`` "cpu", "cuda" or None (warp's default: CUDA when present).
    With ``relaxation`` the static solution is found by dynamic relaxation (fast path).
    See :func:`solve_batch` for the other arguments."""
    return solve_batch(model, [model.materials], device=device, sample_every=sample_every,
                       ke_ie_limit=ke_ie_limit, initial_displacement=initial_displacement,
                       relaxation=relaxation, progress=progress, steady_state_mm=steady_state_mm,
                       mass_scaling=mass_scaling)[0]



@staged("solving")
def solve_batch(model: Model, materials: list[ElementMaterials], plate_displacements: list | None = None,
                device=None, sample_every: int = 200, ke_ie_limit: float = 0.05,
                initial_displacement: np.ndarray | None = None,
                relaxation: DynamicRelaxation | None = None, warm_start: WarmStart | None = None,
                progress: Callable[[float], bool | None] | None = None,
                steady_state_mm: float | None = None, mass_scaling: bool = False,
                plates: list[list[Plate]] | None = None, memory_limit_bytes: int | None = None,
                cpu_workers: int | None = None) -> list[Solution]:
    """Solve B variants of ``model`` that share its mesh and constraints in one batched launch:
    ``materials[b]`` per variant and optionally ``plate_displacements[b]`` (P, 3) mm, or whole
    plate sets ``plates[b]`` (pose, travel, edge and friction per variant; the same P plates in
    the same order with the same contact nodes as the model's, which they replace). All variants
    use the smallest critical step of the batch, so results equal separate solves at that step.
    Variants whose own T4ANP partitions differ (elements grouped by each one's bulk moduli: a
    stiffer skin layer, a gland told from the fat) are solved in one launch per partition
    (:func:`~BreastBiomechLib.solver.host_setup.anp_partition_classes`), so that no variant's
    pressure averaging, and so its solution, depends on the others in its batch.
    ``initial_displacement`` (N, 3) mm starts every variant from rest in that configuration.
    ``warm_start`` (dynamic relaxation, frictionless plates): every variant starts at that
    nearby equilibrium (:class:`~BreastBiomechLib.solver.warm.WarmStart`) with the constraints
    and gravity in full and the plates moving only by their travel's difference from the
    start's; the static solution is the same within the tolerance, reached in fewer iterations,
    or "not converged" past twice the start's iterations (:meth:`WarmStart.bounded`: solve
    those cold). Every ``sample_every`` steps the energies, plate forces and the stable step are sampled and
    ``progress(fraction done)`` is called; returning False cancels the solve (status "cancelled",
    the displacement returned is the last configuration). Dynamic relaxation finds the
    equilibrium, so visco materials enter it fully relaxed. A variant in which an element
    inverts stops there alone (status "inverted elements", its displacement that
    configuration); the others go on.

    ``steady_state_mm`` (physical time only) stops the settling phase early once every model is
    at rest: after the end of loading, when the estimated distance still to travel, max|du| r /
    (1 - r) from the displacement change du between samples and its contraction r, is below
    ``steady_state_mm`` at two samples in a row and KE/IE is below 1e-3. (KE/IE alone would stop
    too early: slow overdamped modes such as sliding on the chest wall carry almost no kinetic
    energy.)

    ``mass_scaling`` (physical time): scale each element's density so that every element has
    the stable step of the median element (and raise the masses further where the stable-step
    check finds the model stiffer), as dynamic relaxation does, but keep the physical load
    history and damping. For quasi-static loading only: inertia is no longer physical (KE/IE
    then measures the fictitious masses), gravity still acts on the physical masses. It pays on
    meshes with slivers or very stiff small elements, whose critical step sets the pace.

    Before anything is allocated the memory the solve needs is estimated and checked against what
    the device has free (or ``memory_limit_bytes``, a cap on a shared machine): a mesh or batch
    that does not fit is refused (:class:`~BreastBiomechLib.solver.memory.TooLargeForMemory`, a
    ValueError) with the estimate and the largest batch that fits.

    On the CPU a mesh numbered scattered (as TetGen leaves it) is solved in a local order and its
    results given back in the mesh's numbering (:mod:`~BreastBiomechLib.solver.ordering`), and a
    batch of several variants is split over ``cpu_workers`` processes (default
    :func:`~BreastBiomechLib.solver.cpu_pool.cpu_workers`: the cores, or BREASTBIOMECH_CPU_WORKERS),
    each chunk at the smallest critical step of its own variants
    (:mod:`~BreastBiomechLib.solver.cpu_pool`)."""
    wp.init()
    device = _device(device)
    if warm_start is not None and relaxation is not None:
        relaxation = warm_start.bounded(relaxation)
    classes = (anp_partition_classes(materials) if anp_mode(model) == k.ANP_WITHIN_MATERIALS
               else np.zeros(len(materials), np.int64))
    if classes.max() > 0:  # sets whose own ANP partitions differ: one launch per partition
        def solve_part(members, part_progress):
            return solve_batch(model, [materials[b] for b in members], _members(plate_displacements, members),
                               device=device, sample_every=sample_every, ke_ie_limit=ke_ie_limit,
                               initial_displacement=initial_displacement, relaxation=relaxation,
                               warm_start=warm_start, progress=part_progress, steady_state_mm=steady_state_mm,
                               mass_scaling=mass_scaling, plates=_members(plates, members),
                               memory_limit_bytes=memory_limit_bytes, cpu_workers=cpu_workers)
        return _by_class(classes, solve_part, progress)
    options = BatchOptions(relaxation=relaxation, warm_start=warm_start, initial_displacement=initial_displacement,
                           sample_every=sample_every, ke_ie_limit=ke_ie_limit, steady_state_mm=steady_state_mm,
                           mass_scaling=mass_scaling, progress=progress, memory_limit_bytes=memory_limit_bytes)
    if initial_displacement is not None and model.prestate is not None:
        raise ValueError("the model starts from its pre-stressed reference state; give no initial_displacement")
    if device.is_cpu and len(materials) > 1:
        workers = cpu_pool.cpu_workers(len(materials)) if cpu_workers is None else min(cpu_workers, len(materials))
        solutions = None if workers < 2 else cpu_pool.solve_on_cores(
            model, materials, plate_displacements, plates, workers, progress, relaxation=relaxation,
            warm_start=warm_start, initial_displacement=initial_displacement, sample_every=sample_every,
            ke_ie_limit=ke_ie_limit, steady_state_mm=steady_state_mm, mass_scaling=mass_scaling,
            memory_limit_bytes=memory_limit_bytes)
        if solutions is not None:
            return solutions
    order = SolverOrder.for_mesh(model.mesh, len(materials)) if device.is_cpu else None
    if order is None:
        return BatchRun(model, materials, device, options, plate_displacements, plates).run()
    c_nodes, _, _ = merged_constraints(model)  # errors that name nodes name the mesh's
    constraint_load_shapes(model, c_nodes)
    options = replace(options, initial_displacement=order.node_values(initial_displacement),
                      warm_start=None if warm_start is None else replace(
                          warm_start, displacement=order.node_values(warm_start.displacement)))
    solutions = BatchRun(order.model(model), [order.materials(m) for m in materials], device, options,
                         plate_displacements, None if plates is None else [order.plates(ps) for ps in plates],
                         element_ids=order.elements).run()
    for s in solutions:
        s.displacement = order.mesh_values(s.displacement)
    return solutions


def _members(per_model: list | None, members: np.ndarray) -> list | None:
    return None if per_model is None else [per_model[b] for b in members]


def _by_class(classes: np.ndarray, solve_part: Callable, progress: Callable[[float], bool | None] | None) -> list[Solution]:
    """The solutions of a batch solved as one launch per class of ``classes`` (B,) in the sets'
    order: ``solve_part(members, part_progress)`` solves the sets ``members``; ``progress`` gets
    the batch's fraction done, and once it returns False the parts not yet started are cancelled
    at their first sample."""
    B = len(classes)
    solutions: list[Solution | None] = [None] * B
    done, cancelled = 0, False

    def part_progress(size: int):
        def report(fraction: float):
            nonlocal cancelled
            if cancelled:
                return False
            if progress is not None and progress((done + fraction * size) / B) is False:
                cancelled = True
                return False
            return None
        return report

    for c in np.unique(classes):
        members = np.flatnonzero(classes == c)
        for b, solution in zip(members, solve_part(members, part_progress(len(members)))):
            solutions[b] = solution
        done += len(members)
    return solutions
