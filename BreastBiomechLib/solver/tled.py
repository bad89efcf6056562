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

import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
import warp as wp

from BreastBiomechLib.solver import kernels as k
from BreastBiomechLib.solver.geometry import MeshGeometry
from BreastBiomechLib.solver.materials import ElementMaterials, element_groups
from BreastBiomechLib.solver.memory import SolveSize, check_fits
from BreastBiomechLib.solver.model import LOAD_SHAPES, Model, Plate
from BreastBiomechLib.solver.ordering import SolverOrder
from BreastBiomechLib.solver.packing import Selection
from BreastBiomechLib.solver.readback import HostCopy
from BreastBiomechLib.solver.relaxation import MM, QUOTIENT_WINDOW, DistanceToRest, RelaxationControl
from BreastBiomechLib.solver.stability import MassScaling, StableStepMonitor
from BreastBiomechLib.solver.warm import WarmStart, ramp_iterations, start_time, started_plates

# models an element-kernel thread computes, by the count of models listed: (up to this many models,
# this many a thread). In a batch the element kernels are bound by their instruction issue (74 % of
# the issue slots busy at 16 and 64 models, Nsight Compute, H200), and a thread that takes several
# models reads and indexes its element's connectivity, derivatives and volume once for them; with
# too few threads an element the GPU has too few to hide latencies (docs/benchmarks.md)
MODELS_PER_THREAD = ((8, 1), (32, 2), (1 << 30, 4))
ELEMENT_FORCES_BLOCK = 128  # threads per block of the element_forces kernels (see solve_batch)
# pairs of steps per CUDA graph: each graph launch costs the GPU about 1.4 us of its own, 0.7 us a
# step in graphs of two steps and 0.15 us in graphs of ten (160k tets, H200, docs/benchmarks.md)
STEP_GRAPH_PAIRS = 5
# a batch is packed down to its models still moving once they are this fraction of it or fewer (see
# :mod:`packing`): a batch of 16 packs four times at most, and a fit's solves took 42.5 s packed at
# half, 43.4 at three quarters and 44.1 at every stop (H200, docs/benchmarks.md)
PACK_AT = 0.5
UNBOUNDED_M = 1e20  # the edge distance (m) of a plate without an edge: never reached
SPRING_PA_PER_MM_MM2_TO_N_PER_M = 1e-3  # (Pa/mm) x mm^2 = 1e3 N/m^3 x 1e-6 m^2
FRICTION_WAVE_CROSSINGS = 6.0  # relaxation with friction loads over this many shear-wave crossings
FLOAT32_ROUNDING = 2.0 ** -24  # float32's relative rounding error (half an ulp of 1)


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


def wave_modulus(mat: ElementMaterials) -> np.ndarray:
    """Per element, the largest small-strain longitudinal (P-wave) modulus (Pa):
    kappa + 4 mu / 3 + 16 eta / 9. The fibre term eta/2 (I4bar - 1)^2 stiffens a uniaxial strain
    e along the fibre by 16 eta / 9 (I4bar - 1 = 4 e / 3 there); along other directions by less."""
    return mat.kappa + 4.0 * mat.mu / 3.0 + 16.0 * mat.eta / 9.0


def wave_speed_ratio(mat: ElementMaterials) -> float:
    """The largest c_dilatational / c_shear = sqrt(wave_modulus / mu) over the elements: how many
    times faster than the slowest shear wave the loads' prescribed motion must stay below."""
    return float(np.max(np.sqrt(wave_modulus(mat) / mat.mu)))


def stress_noise_floor_mm(materials: list[ElementMaterials], length_m: np.ndarray) -> np.ndarray:
    """(B,) the displacement (mm) below which float32 cannot resolve each model's equilibrium:
    float32 rounding of J - 1 times the largest bulk-to-shear modulus ratio, over the median element
    altitude. A volumetric stress kappa (J - 1) is rounded by about kappa x 6e-8, which the shear
    stiffness answers with a strain of that over mu. On a block of 2.5 mm cubes at rest the largest
    nodal change between relaxation updates stays at 0.8e-6-2e-6 mm for nu = 0.49 (kappa / mu = 50)
    and wanders at 2e-5-9e-5 mm for nu = 0.4999 (kappa / mu = 5 000): between a 25th and a third
    of this bound (5.2e-6 and 5.3e-4 mm there)."""
    ratio = np.array([float(np.max(m.kappa / np.maximum(m.mu, 1e-30))) for m in materials])
    return FLOAT32_ROUNDING * ratio * float(np.median(length_m)) / MM


def critical_time_step(model: Model, materials: list[ElementMaterials], length_m: np.ndarray | None = None) -> float:
    """min over elements and batch of L_e / c_d, c_d = sqrt(wave_modulus / rho) (s), the fibres
    counted; ``length_m`` the element altitudes if already computed."""
    if length_m is None:
        length_m = MeshGeometry.of(model.mesh.nodes, model.mesh.tets).length
    return float(min(np.min(length_m / np.sqrt(wave_modulus(m) / m.density)) for m in materials))


def merged_constraints(model: Model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One row per constrained node (node ids, (K, 3) mask, (K, 3) final values in mm): a node in
    several constraints gets the union of their components. The kernel writes each node from one
    thread only. Two different values for one component of one node are an error."""
    cons = model.loading.constraints
    if not cons:
        return np.zeros(0, np.int64), np.zeros((0, 3), bool), np.zeros((0, 3))
    nodes = np.concatenate([c.nodes for c in cons])
    masks = np.concatenate([c.mask for c in cons])
    values = np.concatenate([c.values for c in cons])
    unique, inverse = np.unique(nodes, return_inverse=True)
    mask = np.zeros((len(unique), 3), bool)
    merged = np.zeros((len(unique), 3))
    np.logical_or.at(mask, inverse, masks)
    np.add.at(merged, inverse, np.where(masks, values, 0.0))
    count = np.zeros((len(unique), 3))
    np.add.at(count, inverse, masks.astype(float))
    merged = np.divide(merged, count, out=np.zeros_like(merged), where=count > 0)
    spread = np.zeros((len(unique), 3))
    np.maximum.at(spread, inverse, np.where(masks, np.abs(values - merged[inverse]), 0.0))
    if np.any(spread > 1e-9):
        bad = unique[np.any(spread > 1e-9, axis=1)][:5]
        raise ValueError(f"nodes {bad.tolist()} are given different prescribed values for the same component")
    return unique, mask, merged


def plate_pose(plate: Plate) -> k.PlatePose:
    """The kernels' record of ``plate`` (:class:`kernels.PlatePose`, SI units): its mm
    converted to m, an edgeless plate's face ending at :data:`UNBOUNDED_M`."""
    pose = k.PlatePose()
    pose.point = wp.vec3(*(np.asarray(plate.point, np.float64) * MM))
    pose.normal = wp.vec3(*np.asarray(plate.normal, np.float64))
    pose.motion = wp.vec3(*(np.asarray(plate.displacement, np.float64) * MM))
    pose.edge_direction = wp.vec3(*(np.asarray(plate.edge.direction, np.float64) if plate.edge else np.zeros(3)))
    pose.edge_distance = plate.edge.distance * MM if plate.edge else UNBOUNDED_M
    pose.edge_radius = plate.edge.radius * MM if plate.edge else 1.0
    pose.friction = plate.friction
    return pose


def constraint_load_shapes(model: Model, nodes: np.ndarray) -> np.ndarray:
    """The load curve of each component of the merged constraint rows (``nodes`` from
    :func:`merged_constraints`), as (K, 3) indices into ``LOAD_SHAPES``: a constraint's own shape,
    else the loading's. Two shapes for one non-zero component of one node are an error (a fixed
    component, value 0, is 0 under any curve)."""
    default = LOAD_SHAPES.index(model.loading.load_shape)
    shapes = np.full((len(nodes), 3), default, np.int32)
    chosen = np.zeros((len(nodes), 3), bool)
    for c in model.loading.constraints:
        if c.load_shape is None or not len(c.nodes):
            continue
        rows = np.searchsorted(nodes, c.nodes)
        moving = c.mask & (c.values != 0)
        code = LOAD_SHAPES.index(c.load_shape)
        clash = moving & chosen[rows] & (shapes[rows] != code)
        if np.any(clash):
            bad = c.nodes[np.any(clash, axis=1)][:5]
            raise ValueError(f"nodes {bad.tolist()} are given two load shapes for the same displaced component")
        shapes[rows] = np.where(moving, code, shapes[rows])
        chosen[rows] |= moving
    return shapes


def material_table(materials: list[ElementMaterials]) -> k.MaterialTable:
    """The B sets' materials as the kernels read them (:class:`kernels.MaterialTable`, on the
    current device): one row per group of elements whose float32 mu, kappa, eta and fibre agree in
    every set, model b's entry of row r at r * B + b."""
    f32 = np.float32
    row = element_groups(materials, lambda m: (m.mu.astype(f32), m.kappa.astype(f32), m.eta.astype(f32),
                                               *m.fibre.T.astype(f32)))
    first = np.zeros(int(row.max()) + 1, np.int64)
    first[row] = np.arange(len(row))  # one element of each row

    records = np.stack([np.column_stack([m.mu[first], m.kappa[first], m.eta[first], m.fibre[first]])
                        for m in materials], axis=1)  # (R, B, 6): mu, kappa, eta, fibre
    records = np.ascontiguousarray(records.reshape(-1, 6), dtype=f32).view(k.ElementMaterial.numpy_dtype())
    table = k.MaterialTable()
    table.row = wp.array(row.astype(np.int32), dtype=int)
    table.values = wp.array(records.reshape(-1), dtype=k.ElementMaterial)
    return table


def anp_slots(tets: np.ndarray, materials: list[ElementMaterials], vol: np.ndarray,
              across_materials: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """ANP's averaging slots: one per node and material, so that the nodal pressure is averaged
    over the elements of one material only (materials told apart by their bulk moduli, in every
    parameter set of the batch). Averaging across materials would divide a stiff neighbour's
    pressure by a soft element's bulk modulus, amplifying it by their ratio (10 from fat to
    muscle), and collapse thin soft layers. ``across_materials``: one slot per node, as
    NiftySim's T4ANP (``Model.anp_across_materials``). Returns the slot of each element node
    (M, 4) and each slot's volume (S,) (sum of its elements' volumes, the units of ``vol``)."""
    group = np.zeros(len(tets), np.int64) if across_materials else element_groups(
        materials, lambda m: [np.asarray(m.kappa, np.float64)])
    groups = int(group.max()) + 1
    pairs = tets.astype(np.int64) * groups + group[:, None]
    if int(pairs.max()) < 8 * pairs.size:  # number the (node, material) pairs present, in their order
        present = np.zeros(int(pairs.max()) + 1, bool)
        present[pairs.ravel()] = True
        slots = (np.cumsum(present) - 1)[pairs]
        n_slots = int(np.count_nonzero(present))
    else:  # very many materials: sort the pairs instead
        unique_pairs, slots = np.unique(pairs.ravel(), return_inverse=True)
        n_slots = len(unique_pairs)
    slots = slots.reshape(tets.shape).astype(np.int32)
    return slots, np.bincount(slots.ravel(), weights=np.repeat(vol, 4), minlength=n_slots)


def anp_mode(model: Model) -> int:
    """The element kernels' ANP mode for ``model`` (``kernels.ANP_*``)."""
    if model.formulation != "T4ANP":
        return k.ANP_OFF
    return k.ANP_ACROSS_MATERIALS if model.anp_across_materials else k.ANP_WITHIN_MATERIALS


def plate_sets_of_batch(model: Model, n_models: int, plate_displacements: list | None = None,
                        plates: list[list[Plate]] | None = None) -> list[list[Plate]]:
    """The plates of each of the ``n_models`` models of a batch: the model's own, with
    ``plate_displacements[b]`` (P, 3) mm as model b's travel, or the given ``plates[b]`` (which
    must be the model's plates in number, order and contact nodes: the contact launches share
    the node lists)."""
    own = model.loading.plates
    if plates is not None and plate_displacements is not None:
        raise ValueError("give either plate_displacements or plates per model, not both")
    if plates is None:
        if plate_displacements is None:
            return [own] * n_models
        if len(plate_displacements) != n_models:
            raise ValueError("give one plate displacement set per material set")
        plates = []
        for motion in plate_displacements:
            motion = np.asarray(motion, float).reshape(len(own), 3)
            plates.append([replace(p, displacement=d) for p, d in zip(own, motion)])
        return plates
    if len(plates) != n_models:
        raise ValueError(f"give one plate set per material set ({n_models}), not {len(plates)}")
    for b, ps in enumerate(plates):
        if len(ps) != len(own) or any(not np.array_equal(p.slave_nodes, o.slave_nodes) for p, o in zip(ps, own)):
            raise ValueError(f"plate set {b} must hold the model's {len(own)} plates with their contact nodes "
                             "(only pose, travel, edge and friction may differ between the models of a batch)")
        for p in ps:
            p.check_clear_of(model.start_positions[p.slave_nodes])
    return plates


def element_lanes(width: int) -> int:
    """Threads per element of the element kernels for ``width`` listed models: each thread
    computes up to :data:`MODELS_PER_THREAD`'s number of them, reading its element's own data
    once."""
    per_thread = next(k for most, k in MODELS_PER_THREAD if width <= most)
    return -(-width // per_thread)


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


def _step_too_large(t: float, stable: float, dt: float) -> str:
    return (f"at t = {t:.4g} s the model's stable time step is at most {stable:.3g} s, below the step used "
            f"({dt:.3g} s): the solve would diverge. Lower the safety factor or set a smaller time_step")


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


def relaxation_load_iterations(model: Model, materials: list[ElementMaterials], plate_sets: list[list[Plate]],
                               relaxation: DynamicRelaxation, length_m: np.ndarray | None = None) -> np.ndarray:
    """(B,) the iterations over which dynamic ``relaxation`` applies each variant's load
    (:meth:`DynamicRelaxation.load_iterations_for` with the variant's fully relaxed
    ``materials[b]``, plates ``plate_sets[b]``, the model's constraints and extent), as
    :func:`solve_batch` does; ``length_m``: the elements' altitudes if already computed."""
    nodes = model.mesh.nodes * MM
    if length_m is None:
        length_m = MeshGeometry.of(model.mesh.nodes, model.mesh.tets).length
    constrained = max([np.abs(c.values).max(initial=0.0) for c in model.loading.constraints] + [0.0])
    extent = float(np.max(np.ptp(nodes, axis=0)))
    typical = float(np.median(length_m))
    return np.array([
        relaxation.load_iterations_for(max([np.abs(p.displacement).max() for p in ps] + [constrained]),
                                       wave_speed_ratio(m), typical, model.safety,
                                       extent if any(p.friction > 0 for p in ps) else 0.0)
        for m, ps in zip(materials, plate_sets)])


def solve_batch(model: Model, materials: list[ElementMaterials], plate_displacements: list | None = None,
                device=None, sample_every: int = 200, ke_ie_limit: float = 0.05,
                initial_displacement: np.ndarray | None = None,
                relaxation: DynamicRelaxation | None = None, warm_start: WarmStart | None = None,
                progress: Callable[[float], bool | None] | None = None,
                steady_state_mm: float | None = None, mass_scaling: bool = False,
                plates: list[list[Plate]] | None = None, memory_limit_bytes: int | None = None) -> list[Solution]:
    """Solve B variants of ``model`` that share its mesh and constraints in one batched launch:
    ``materials[b]`` per variant and optionally ``plate_displacements[b]`` (P, 3) mm, or whole
    plate sets ``plates[b]`` (pose, travel, edge and friction per variant; the same P plates in
    the same order with the same contact nodes as the model's, which they replace). All variants
    use the smallest critical step of the batch, so results equal separate solves at that step.
    ``initial_displacement`` (N, 3) mm starts every variant from rest in that configuration.
    ``warm_start`` (dynamic relaxation, frictionless plates): every variant starts at that
    nearby equilibrium (:class:`~BreastBiomechLib.solver.warm.WarmStart`) with the constraints
    and gravity in full and the plates moving only by their travel's difference from the
    start's; the static solution is the same within the tolerance, reached in fewer iterations.
    Every ``sample_every`` steps the energies, plate forces and the stable step are sampled and
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
    results given back in the mesh's numbering (:mod:`~BreastBiomechLib.solver.ordering`)."""
    wp.init()
    device = _device(device)
    order = SolverOrder.for_mesh(model.mesh, len(materials)) if device.is_cpu else None
    if order is None:
        return _solve_batch_in_order(model, materials, plate_displacements, device, sample_every, ke_ie_limit,
                                     initial_displacement, relaxation, warm_start, progress, steady_state_mm,
                                     mass_scaling, plates, memory_limit_bytes)
    c_nodes, _, _ = merged_constraints(model)  # errors that name nodes name the mesh's
    constraint_load_shapes(model, c_nodes)
    solutions = _solve_batch_in_order(
        order.model(model), [order.materials(m) for m in materials], plate_displacements, device, sample_every,
        ke_ie_limit, order.node_values(initial_displacement), relaxation,
        None if warm_start is None else replace(warm_start, displacement=order.node_values(warm_start.displacement)),
        progress, steady_state_mm, mass_scaling, None if plates is None else [order.plates(ps) for ps in plates],
        memory_limit_bytes, element_ids=order.elements)
    for s in solutions:
        s.displacement = order.mesh_values(s.displacement)
    return solutions


def _solve_batch_in_order(model: Model, materials: list[ElementMaterials], plate_displacements: list | None,
                          device, sample_every: int, ke_ie_limit: float, initial_displacement: np.ndarray | None,
                          relaxation: DynamicRelaxation | None, warm_start: WarmStart | None,
                          progress: Callable[[float], bool | None] | None, steady_state_mm: float | None,
                          mass_scaling: bool, plates: list[list[Plate]] | None, memory_limit_bytes: int | None,
                          element_ids: np.ndarray | None = None) -> list[Solution]:
    """:func:`solve_batch` in the model's own numbering; ``element_ids[e]``: the name of element e
    in messages (None: e)."""
    wp.init()
    device = _device(device)
    if warm_start is not None and (relaxation is None or initial_displacement is not None):
        raise ValueError("a warm start is a start of dynamic relaxation: give a relaxation and no initial_displacement")
    if initial_displacement is not None and model.prestate is not None:
        raise ValueError("the model starts from its pre-stressed reference state; give no initial_displacement")
    if steady_state_mm is not None and (relaxation is not None or steady_state_mm <= 0):
        raise ValueError("steady_state_mm is a positive distance (mm) for physical-time solves; dynamic "
                         "relaxation has its own tolerance")
    if mass_scaling and relaxation is not None:
        raise ValueError("mass_scaling is an option of physical-time solves; dynamic relaxation always scales masses")
    scaled = mass_scaling or relaxation is not None
    # B: the models of the batch as the device holds them, n_sets as given; B falls where a
    # relaxation packs the batch down to its moving models (``members``: the sets they are)
    B, N, M = len(materials), len(model.mesh.nodes), len(model.mesh.tets)
    n_sets = B
    if B == 0:
        raise ValueError("solve_batch needs at least one material set")
    for mat in materials:
        if len(mat.mu) != M:
            raise ValueError(f"a material set has {len(mat.mu)} elements, the mesh has {M}")
    if relaxation is not None:
        materials = [mat.long_term() for mat in materials]
    plate_sets = plate_sets_of_batch(model, B, plate_displacements, plates)
    P = len(model.loading.plates)

    geometry = MeshGeometry.of(model.mesh.nodes, model.mesh.tets)  # computed once per mesh
    nodes, tets, dhdx, vol, length = geometry.nodes_m, geometry.tets, geometry.dhdx, geometry.vol, geometry.length
    slots, slot_volume = anp_slots(tets, materials, vol, model.anp_across_materials)
    S = len(slot_volume)
    check_fits(SolveSize(B, N, M, S, max(m.prony_terms for m in materials),
                         sum(len(p.slave_nodes) for p in model.loading.plates), P), device, memory_limit_bytes)
    if scaled:  # mass scaling: every element's stable step becomes dt / safety
        dt = model.safety * float(np.median(length / np.sqrt(wave_modulus(materials[0]) / materials[0].density)))
        densities = [wave_modulus(mat) * (dt / (model.safety * length)) ** 2 for mat in materials]
        if relaxation is None:  # physical time: only add mass, where elements are below the step
            densities = [np.maximum(rho, mat.density) for rho, mat in zip(densities, materials)]
    else:
        densities = [mat.density for mat in materials]
        dt = model.time_step or model.safety * critical_time_step(model, materials, length)
    if relaxation is None:
        totals = np.full(B, model.loading.total_time)
        n_steps = int(math.ceil((model.loading.total_time + model.loading.settle_time) / dt))
    else:  # fictitious time: each model loads as slowly as its own materials and travel need
        load_iterations = relaxation_load_iterations(model, materials, plate_sets, relaxation, length)
        totals = load_iterations * dt
        n_steps = max(relaxation.max_iterations, 2 * int(load_iterations.max()))
        cold_load_time = totals  # sets the damping before the first update, warm or cold
        if warm_start is not None:
            plate_sets = started_plates(model, warm_start, plate_sets)
            ratios = [wave_speed_ratio(m) for m in materials]
            totals = start_time(ramp_iterations(relaxation, plate_sets, ratios, float(np.median(length)),
                                                model.safety), dt)
        # the scale of each model's lowest eigenvalue: mean mu / rho over the volume (m^2/s^2)
        speed_squared = np.array([float(np.sum(vol * mat.mu / rho) / np.sum(vol))
                                  for mat, rho in zip(materials, densities)])
        noise_floor = stress_noise_floor_mm(materials, length)
        sample_every = relaxation.update_every
    total = float(totals.max())  # the batch's loading ends with its slowest model's
    # nodal masses (kg) of the B models, models innermost (node a of model b at a*B + b): a quarter
    # of each element's mass at its nodes
    mass = geometry.lumped(densities)
    weight = geometry.lumped([m.density for m in materials])  # physical masses: gravity acts on these
    if np.any(mass <= 0):
        raise ValueError("some nodes belong to no element (zero mass); remove unused nodes")
    load_shape = LOAD_SHAPES.index(model.loading.load_shape)  # plates and gravity; constraints per component

    f32 = np.float32
    with wp.ScopedDevice(device):

        def arr(values, dtype):
            return wp.array(np.ascontiguousarray(values, dtype=np.int32 if dtype is int else f32), dtype=dtype)

        d_tets = wp.array(tets, dtype=int)
        d_dhdx = wp.array(dhdx.astype(f32), dtype=wp.vec3)
        d_vol = arr(vol, float)
        # one material (or ANP across materials): the slots are the nodes, and the kernels' reads of
        # both fall on one array (cached after the first)
        slots_are_nodes = bool(np.array_equal(slots, tets))
        d_slots = d_tets if slots_are_nodes else wp.array(slots, dtype=int)
        d_slotvol = arr(slot_volume, float)
        d_mass = arr(mass, float)
        def interleaved(per_model):
            """(B, M, ...) values of the B models as the kernels hold them: element e of model b at e*B + b."""
            first = np.shape(per_model[0])
            return np.stack(per_model, axis=1).reshape((first[0] * len(per_model),) + first[1:])

        d_materials = material_table(materials)
        # visco: K Prony terms per element (padded with g = 0), decay exp(-dt / tau) per step
        K = max(m.prony_terms for m in materials)
        prony_g = interleaved([np.pad(m.prony_g, ((0, 0), (0, K - m.prony_terms))) for m in materials])
        prony_tau = interleaved([np.pad(m.prony_tau, ((0, 0), (0, K - m.prony_terms)), constant_values=1.0)
                                    for m in materials])
        d_prony_g = arr(prony_g.reshape(-1) if K else np.zeros(1), float)
        d_prony_decay = arr(np.exp(-dt / prony_tau).reshape(-1) if K else np.zeros(1), float)
        visco_state = wp.zeros(max(B * M * K, 1), dtype=wp.mat33)
        if model.prestate is not None:  # at rest in the pre-stressed state
            initial_displacement = model.prestate.displacement
        if warm_start is not None:
            initial_displacement = warm_start.displacement
        u0 = np.zeros((B * N, 3)) if initial_displacement is None else np.repeat(
            np.asarray(initial_displacement, float).reshape(N, 3) * MM, B, axis=0)
        # the state: displacement u (m), its float32 rounding remainder and the last increment
        u, low, du = arr(u0, wp.vec3), wp.zeros(B * N, dtype=wp.vec3), wp.zeros(B * N, dtype=wp.vec3)
        scratch = wp.zeros(B * N, dtype=wp.vec3)
        forces = wp.zeros((3, B * N), dtype=float)  # component planes (see kernels)
        anp_sums = wp.zeros(B * S, dtype=float)
        clock = wp.zeros(2, dtype=int)  # the step: [as the element kernel reads it, as the node kernel does]
        inverted = wp.zeros(4 * B, dtype=int)  # per model: count, first element, its step, frozen
        plate_force = wp.zeros(max(3 * B * P, 1), dtype=float)  # model b's plate p at 3 (b P + p): x, y, z (N)
        # gravity acts on the physical masses, also where dynamic relaxation scales them
        # with a pre-stressed reference state its gravity acts from the start, changing to the
        # loading's gravity over the load
        start_gravity = np.zeros(3) if model.prestate is None else model.prestate.gravity
        d_body_start = arr(weight[:, None] * start_gravity, wp.vec3)
        d_body_force = arr(weight[:, None] * (model.loading.gravity - start_gravity), wp.vec3)
        # dynamic relaxation starts critically damped for a mode of period ~ the loading time
        damping = np.full(B, model.damping) if relaxation is None else 4.0 * np.pi / cold_load_time
        # a warm start's damping never exceeds its start's lowest mode critical damping: the first
        # Rayleigh quotients after it measure the start's local misfit (high modes), not the lowest
        # mode, and would overdamp the approach (and mislead the distance estimate)
        damping_cap = np.full(B, np.inf)
        if warm_start is not None and np.isfinite(warm_start.lowest_eigenvalue):
            damping_cap = warm_start.critical_damping(speed_squared)
            damping = np.minimum(damping, damping_cap)
        d_totals = arr(totals, float)
        d_damping = arr(damping, float)
        loads = k.NodeLoads()
        loads.mass, loads.body_start, loads.body_force = d_mass, d_body_start, d_body_force
        loads.damping, loads.t_total, loads.load_shape, loads.dt = d_damping, d_totals, load_shape, float(dt)
        active = np.ones(n_sets, np.int32)  # the sets moving as of the last sample the host has read
        members = np.arange(n_sets)  # the set of each model of the batch as packed

        def model_list(flags):
            """The kernels' list of models (see :mod:`kernels`): the flagged models, then padding."""
            chosen = np.flatnonzero(flags)
            listing = np.zeros(B, np.int32)
            listing[:len(chosen)] = chosen
            return listing

        d_moving = arr(model_list(active), int)  # the models the steps compute

        def stop_models():
            """The models no longer ``active`` out of the steps' list (the steps leave them alone
            already: they are frozen, see :mod:`relaxation`)."""
            d_moving.assign(model_list(active[members]))

        c_nodes, c_mask, c_vals = merged_constraints(model)
        n_con = len(c_nodes)
        d_cnodes = arr(c_nodes, int)
        d_cmask = arr(c_mask.astype(f32), wp.vec3)
        constraints = k.NodeConstraints()
        row_of_node = np.full(N, -1, np.int32)
        row_of_node[c_nodes] = np.arange(n_con)
        constraints.constrained = arr(row_of_node, int)
        constraints.mask = d_cmask if n_con else arr(np.zeros((1, 3)), wp.vec3)
        constraints.shapes = wp.array(constraint_load_shapes(model, c_nodes).reshape(-1, 3) if n_con
                                      else np.zeros((1, 3), np.int32), dtype=wp.vec3i)
        constraints.value = arr(np.repeat(c_vals * MM, B, axis=0) if n_con else np.zeros((1, 3)), wp.vec3)
        constraints.n_constrained = n_con

        # surface supports: springs (with the internal forces) and, sliding, the normal projection
        d_supports = []
        sliding = [s for s in model.loading.supports if s.mode == "sliding" and len(s.nodes)]
        slide = np.full((N, max(len(sliding), 1)), -1, np.int32)
        offset = 0
        for column, support in enumerate(sliding):
            slide[support.nodes, column] = offset + np.arange(len(support.nodes))
            offset += len(support.nodes)
        constraints.slide = wp.array(slide, dtype=int)
        constraints.n_sliding = len(sliding)
        constraints.slide_normals = arr(np.concatenate([s.normals for s in sliding]) if sliding
                                        else np.zeros((1, 3)), wp.vec3)
        for support in model.loading.supports:
            if (support.normal_stiffness > 0 or support.tangential_stiffness > 0) and len(support.nodes):
                spring = np.stack([support.normal_stiffness * support.areas,
                                   support.tangential_stiffness * support.areas],
                                  axis=1) * SPRING_PA_PER_MM_MM2_TO_N_PER_M
                d_supports.append((len(support.nodes), arr(support.nodes, int), arr(support.normals, wp.vec3),
                                   arr(spring, wp.vec2)))

        # the plates' poses, travel and friction per model (model b's plate p at b * P + p); a
        # node may touch several plates, in turn; friction state per contact slot and model
        plates = k.PlateContact()
        contact_slot = np.full((N, max(P, 1)), -1, np.int32)
        n_slots = 0
        plate_slots = []  # plate p's slots: (first, count)
        for p, plate in enumerate(model.loading.plates):
            contact_slot[plate.slave_nodes, p] = n_slots + np.arange(len(plate.slave_nodes))
            plate_slots.append((n_slots, len(plate.slave_nodes)))
            n_slots += len(plate.slave_nodes)
        every_plate = [p for ps in plate_sets for p in ps]
        plates.slot = wp.array(contact_slot, dtype=int)
        plates.n_plates = P
        plates.x0 = arr(nodes, wp.vec3)
        plates.pose = wp.array([plate_pose(p) for p in every_plate] or [k.PlatePose()], dtype=k.PlatePose,
                               device=device)
        plates.anchor = wp.zeros(max(B * n_slots, 1), dtype=wp.vec3)
        plates.touching = wp.zeros(max(B * n_slots, 1), dtype=int)
        plates.force = wp.zeros(max(B * n_slots, 1), dtype=wp.vec3)
        anp = anp_mode(model)
        formulation = k.element_kernels(anp, K > 0, slots_are_nodes)  # this formulation's kernels
        node_update = k.node_kernel(bool(np.any(start_gravity) or np.any(model.loading.gravity)),
                                    any(p.friction > 0 for p in every_plate), len(sliding) > 0)

        every_model = arr(model_list(np.ones(B)), int)
        probe_clock = wp.zeros(2, dtype=int)

        def internal_force(state, out, sums_buffer, flags, models=None, width=None, update_state=0,
                           cleared=False, step_clock=None):
            """Internal nodal forces of ``state`` into ``out`` (ANP sums in ``sums_buffer``)
            for the first ``width`` models of the list ``models`` (the others' stay zero; None:
            every model of the batch);
            ``update_state`` advances the visco state variables by one step; ``cleared``: ``out``
            and ``sums_buffer`` are zero already (the step kernels clear them). A step passes
            its clock (see ``kernels.element_kernels``' element_forces); a probe leaves it alone."""
            if models is None:
                models, width = every_model, B
            if not cleared:
                out.zero_()
                sums_buffer.zero_()
            # a thread per element and model, or (lanes < width) per element and several models
            lanes = element_lanes(width)
            shared = [lanes] if lanes < width else []
            if anp != k.ANP_OFF:
                wp.launch(formulation.nodal_pressure_shared if shared else formulation.nodal_pressure, lanes * M,
                          [state, d_tets, d_slots, d_dhdx, d_vol, d_materials, B, models, width, sums_buffer]
                          + shared)
            # blocks of 128 threads: at its register count the kernel fits 7 of them on an SM
            # against 3 of 256, so a lone 160k-tet model's elements take 1.35 waves, not 1.58
            # (4.5 % less time, H200, docs/benchmarks.md)
            wp.launch(formulation.element_forces_shared if shared else formulation.element_forces, lanes * M,
                      [state, d_tets, d_dhdx, d_vol, d_materials, d_slots, sums_buffer, d_slotvol, K, d_prony_g,
                       d_prony_decay, visco_state, update_state, B, probe_clock if step_clock is None else step_clock,
                       models, width, out, flags] + shared,
                      block_dim=ELEMENT_FORCES_BLOCK)
            for n_sup, d_snodes, d_snormals, d_sstiff in d_supports:
                wp.launch(k.support_springs, width * n_sup, [state, d_snodes, d_snormals, d_sstiff, B, models, width,
                                                             out])

        def one_step(width):
            """One step of the ``width`` moving models: converged models stand still, and their
            threads are not launched."""
            internal_force(u, forces, anp_sums, inverted, d_moving, width, update_state=1, cleared=True,
                           step_clock=clock)
            wp.launch(node_update, width * N, [u, low, du, forces, anp_sums, loads, constraints, plates, d_moving,
                                               width, B, clock, inverted])

        def two_steps(width):
            one_step(width)
            one_step(width)

        graphs = {}  # on CUDA: (pairs of steps, count of moving models) -> a graph of those steps

        def launch_width():
            """Threads per element (node) the steps launch: the moving models' count (it only
            falls, so a batch captures one graph per count it passes through)."""
            return int(np.count_nonzero(active))

        kept = {}  # the results of sets packed out of the batch (see keep_results)

        def keep_results(leaving):
            """Device copies, into arrays of every set, of what the end of the solve reads of the
            selected models ``leaving`` of the batch as packed (positioned as their sets):
            displacement, relaxation outcome, masses."""
            per_model = [("displacement", u)]
            if relaxation is not None:
                per_model += [(name, getattr(control.state, name))
                              for name in ("converged_at", "estimated_error", "lowest")]
            if scaled:
                per_model += [("mass", scaling.mass_float64), ("growth", scaling.growth),
                              ("stable", scaling.stable), ("rescales", scaling.rescales)]
            for name, array in per_model:
                if name not in kept:
                    shape = array.shape[:-1] + (array.shape[-1] // B * n_sets,)
                    kept[name] = wp.zeros(shape, dtype=array.dtype)
                leaving.put(array, kept[name], n_sets)

        kinetic = wp.zeros(B, dtype=float)
        internal = wp.zeros(B, dtype=float)
        history = {"time": [], "kinetic": [], "internal": [], "plate_forces": [], "stable_time_step": []}
        status, message = "completed", "completed"
        ke_ie_end_of_loading = float("nan")
        chunk = max(2, sample_every - sample_every % 2)
        done = 0
        estimated_error = np.full(B, np.nan)
        # a warm start's damping is capped by its start's lowest mode (critically damped at most,
        # so no overdamped creep to mistake for rest): see the class docstring
        warm = warm_start is not None
        window = 1 if warm else QUOTIENT_WINDOW
        converged_forces = np.zeros((B, P, 3))  # a relaxation's plate forces at the sample it converged
        settled_checks = 0
        distance_to_rest = DistanceToRest(u, B)
        anp_tmp = wp.zeros(B * S, dtype=float)
        no_flags = wp.zeros(4 * B, dtype=int)
        failed: dict[int, str] = {}  # models stopped by an inverted element: their message

        def probe_force(state, out):
            """Internal forces for diagnostics: no visco update, inverted elements not recorded."""
            internal_force(state, out, anp_tmp, no_flags)

        if relaxation is not None:
            # the state and forces of a reference renewed every QUOTIENT_WINDOW updates: the
            # Rayleigh quotient of the change over one to QUOTIENT_WINDOW whole update intervals
            # (single-step changes near rest are float32 noise, whose quotient grows towards the
            # highest modes and overdamps the slow ones; over longer windows a slow mode's motion
            # adds up while faster ones' does not)
            f_curr, f_last = wp.zeros((3, B * N), dtype=float), wp.zeros((3, B * N), dtype=float)
            u_last = wp.clone(u)
            probe_force(u_last, f_last)
            stiffness, inertia = wp.zeros(B, dtype=float), wp.zeros(B, dtype=float)
            control = RelaxationControl(totals, damping, d_damping, damping_cap, noise_floor, dt,
                                        relaxation.tolerance_mm, warm)
        monitor = StableStepMonitor(probe_force, d_mass, B, N, 1e-3 * float(np.median(length)), d_cnodes, d_cmask)
        # mass scaling: where the model is stiffer than the element estimate (or got stiffer as it
        # deformed) its fictitious masses grow so that the step stays stable (see MassScaling)
        scaling = MassScaling(d_mass, mass, dt, B) if scaled else None
        # what the host reads of each sample, copied back together (see :mod:`readback`)
        sampled = {name: HostCopy(array) for name, array in (("kinetic", kinetic), ("internal", internal),
                                                             ("plate_force", plate_force), ("inverted", inverted))}
        # the wall time spans the device's work and the host's control of it; the arrays above
        # (the power iteration's random start among them) are set-up, like the mesh's
        wp.synchronize_device(device)
        started = time.perf_counter()
        monitor.advance(u, iterations=20)
        if scaled:
            scaling.apply(monitor, inverted)
        # the host waits for the estimate only where the steps must be checked against it first
        stable_step = None if scaled else monitor.stable_step()

        def sample(renew: bool = True):
            """The device work of a sample, before anything is read back: energies, the forces
            at u (relaxation), a power iteration, the relaxation's Rayleigh-quotient terms (and,
            ``renew``, u and its forces as their next reference), the displacement change
            since the last sample, the plates' forces in the last step, mass scaling and the
            relaxation's decisions."""
            kinetic.zero_()
            internal.zero_()
            # kinetic energy at the half step n - 1/2 and the internal energy averaged over u_n and
            # u_{n-1}: the pair the central-difference scheme conserves to second order
            k.reduction_launch(k.energies, B, N, [du, d_mass, float(dt), N, kinetic])
            wp.launch(k.perturbed, B * N, [u, du, -1.0, scratch])  # u_(n-1)
            for state in (u, scratch):
                k.reduction_launch(k.internal_energy, B, M, [state, d_tets, d_dhdx, d_vol, d_materials, N, M,
                                                             internal])
            if relaxation is not None:  # the relaxation update needs the same forces
                probe_force(u, f_curr)
            monitor.advance(u, base_force=f_curr if relaxation is not None else None)
            if relaxation is not None:
                for a in (stiffness, inertia):
                    a.zero_()
                k.reduction_launch(k.relaxation_terms, B, N, [u, u_last, f_curr, f_last, d_mass, N, stiffness, inertia])
                if renew:
                    wp.copy(u_last, u)
                    wp.copy(f_last, f_curr)
            distance_to_rest.measure(u)
            plate_force.zero_()
            for p, (first, count) in enumerate(plate_slots):
                k.reduction_launch(k.plate_forces, B, count, [plates.force, B, first, count, p, P, inverted,
                                                              plate_force])
            if scaled:
                scaling.apply(monitor, inverted)
            if relaxation is not None:
                control.update(distance_to_rest, kinetic, internal, stiffness, inertia, inverted, clock)
            for copy in sampled.values():
                copy.refresh()

        # on CUDA one graph launch and one wait per sample instead of some thirty of each; each
        # kind of sample captured when first needed, so the host captures while the GPU steps
        sample_graphs = {}

        def enqueue_sample(renew):
            """A sample's device work (see :func:`sample`): on CUDA its graph's launch."""
            if not device.is_cuda:
                sample(renew)
                return
            if renew not in sample_graphs:
                with wp.ScopedCapture() as capture:
                    sample(renew)
                sample_graphs[renew] = capture.graph
            wp.capture_launch(sample_graphs[renew])

        samples = 0
        # a relaxation's decisions are the device's: after each sample the next steps (a quarter of
        # an interval) are enqueued before the host reads it, and run while it does
        lead = max(1, chunk // 8) if relaxation is not None else 0  # pairs of steps
        ahead = 0  # pairs of steps of the current interval enqueued before the last sample was read
        sample_done = wp.Event(device) if device.is_cuda else None  # recorded after each sample's copies

        def enqueue_steps(pairs):
            """``pairs`` pairs of steps of the models the host knows to be moving: on CUDA graphs of
            :data:`STEP_GRAPH_PAIRS` pairs, then graphs of one pair for the rest."""
            width = launch_width()
            if not device.is_cuda:
                for _ in range(pairs):
                    two_steps(width)
                return
            groups, rest = divmod(pairs, STEP_GRAPH_PAIRS)
            for size, count in ((STEP_GRAPH_PAIRS, groups), (1, rest)):
                if count and (size, width) not in graphs:
                    with wp.ScopedCapture() as capture:
                        for _ in range(size):
                            two_steps(width)
                    graphs[size, width] = capture.graph
                for _ in range(count):
                    wp.capture_launch(graphs[size, width])

        def interval(after):
            """Pairs of steps of the sampling interval after step ``after``."""
            return min(chunk, n_steps - after + (n_steps - after) % 2) // 2

        def pack():
            """The batch packed down to its models still ``active``, in their order (device
            work, after the steps already enqueued: see :mod:`packing`); the others' results
            kept (:func:`keep_results`). The old arrays and graphs go: CUDA frees them in the
            stream's order, after the work enqueued on them."""
            nonlocal B, members, u, low, du, scratch, forces, anp_sums, anp_tmp, inverted, no_flags, plate_force
            nonlocal d_materials, d_prony_g, d_prony_decay, visco_state, d_mass, d_damping, d_totals, d_body_start
            nonlocal d_body_force, every_model, d_moving
            nonlocal kinetic, internal, f_curr, f_last, u_last, stiffness, inertia
            stays = active[members] == 1
            staying = Selection(np.flatnonzero(stays), B, device)
            leaving = np.flatnonzero(~stays)
            keep_results(Selection(leaving, B, device, positions=members[leaving]))
            for name in ("kinetic", "plate_forces"):  # at rest, as a frozen model in the batch: no motion, no contact
                latest[name] = latest[name].copy()  # (the history holds the sample's own)
                latest[name][members[leaving]] = 0.0
            graphs.clear()
            sample_graphs.clear()

            # one array at a time, each old one freed as its new one replaces it: the packing needs
            # no more memory than the batch plus its largest array's share of the models kept
            take = staying.take
            u = take(u)
            low = take(low)
            du = take(du)
            scratch = take(scratch)
            forces = take(forces)
            anp_sums = take(anp_sums)
            anp_tmp = take(anp_tmp)
            inverted = take(inverted, 4)
            no_flags = take(no_flags, 4)
            plate_force = take(plate_force, 3 * P)
            table = k.MaterialTable()
            table.row, table.values = d_materials.row, take(d_materials.values)
            d_materials = table
            d_prony_g = take(d_prony_g, K)
            d_prony_decay = take(d_prony_decay, K)
            visco_state = take(visco_state, K)
            d_mass = loads.mass = take(d_mass)
            d_damping = loads.damping = take(d_damping)
            d_totals = loads.t_total = take(d_totals)
            d_body_start = loads.body_start = take(d_body_start)
            d_body_force = loads.body_force = take(d_body_force)
            constraints.value = take(constraints.value)
            plates.pose = take(plates.pose, P)
            plates.anchor = take(plates.anchor)
            plates.touching = take(plates.touching)
            plates.force = take(plates.force)
            kinetic = take(kinetic)
            internal = take(internal)
            if relaxation is not None:
                f_curr = take(f_curr)
                f_last = take(f_last)
                u_last = take(u_last)
                stiffness = take(stiffness)
                inertia = take(inertia)
                control.keep(staying, d_damping)
            distance_to_rest.keep(staying)
            monitor.keep(staying, d_mass)
            if scaling is not None:
                scaling.keep(staying, d_mass)
            members, B = members[staying.models], len(staying)
            every_model = arr(model_list(np.ones(B)), int)
            d_moving = arr(model_list(active[members]), int)
            for name, array in (("kinetic", kinetic), ("internal", internal), ("plate_force", plate_force),
                                ("inverted", inverted)):
                sampled[name].follow(array)

        latest = {}  # of_sets' last values of every set, by name

        def of_sets(values, name):
            """``values`` of the batch as packed, in their sets' places: a set packed out keeps its
            latest value of that ``name`` (None: zero, and nothing kept)."""
            out = np.zeros((n_sets,) + values.shape[1:], values.dtype)
            if name in latest:
                out[:] = latest[name]
            out[members] = values
            if name is not None:
                latest[name] = out
            return out

        if not scaled and dt > stable_step.min():
            status, message = "unstable", _step_too_large(0.0, stable_step.min(), dt)
        while status == "completed" and done < n_steps:
            pairs = interval(done)
            enqueue_steps(pairs - ahead)
            done += 2 * pairs
            samples += 1
            renew = relaxation is None or samples % window == 0
            enqueue_sample(renew)
            if sample_done is not None:
                wp.record_event(sample_done)
            ahead = min(lead, interval(done))
            if ahead:
                enqueue_steps(ahead)
            ke = of_sets(sampled["kinetic"].read(sample_done).astype(float), "kinetic")
            ie = of_sets(0.5 * sampled["internal"].read(sample_done).astype(float), "internal")
            history["time"].append(done * dt)
            history["kinetic"].append(ke)
            history["internal"].append(ie)
            history["plate_forces"].append(of_sets(sampled["plate_force"].read(sample_done)[: 3 * B * P]
                                                   .reshape(B, P, 3).astype(float), "plate_forces"))
            flags = of_sets(sampled["inverted"].read(sample_done).reshape(B, 4), "flags")
            for b in np.flatnonzero((flags[:, 0] > 0) & (active == 1)):
                count, element, at = flags[b, :3]
                element = element if element_ids is None else int(element_ids[element])
                failed[int(b)] = (f"{count} element(s) inverted (J <= 0) at step {at} (t = {at * dt:.4g} s), first "
                                  f"element {element}; the displacement returned is that configuration. Reduce the "
                                  "load, refine the mesh there or check the constraints")
            # frozen by the kernels; the other models of the batch go on
            moving = np.where(flags[:, 0] > 0, 0, active)
            if not moving.any():
                active[:] = moving
                break
            alive = np.array([b not in failed for b in range(n_sets)])
            if not np.all(np.isfinite(ke[alive])) or not np.all(np.isfinite(ie[alive])):
                status, message = "unstable", (f"the solution diverged by step {done + 2 * ahead}; reduce the time "
                                               f"step (now {dt:.3g} s) or the safety factor")
                break
            stable_step = of_sets(monitor.stable_step(sample_done), "stable_time_step")
            stable_step[~alive] = np.inf  # a frozen model's step no longer matters
            history["stable_time_step"].append(stable_step)
            if not scaled and dt > stable_step.min():
                status, message = "unstable", _step_too_large(done * dt, stable_step.min(), dt)
                break
            if progress is not None and progress(done / n_steps) is False:
                status, message = ("cancelled", f"cancelled after {done + 2 * ahead} steps; the displacement "
                                   "returned is that state")
                break
            if np.isnan(ke_ie_end_of_loading) and done * dt >= total - 0.5 * dt:
                ke_ie_end_of_loading = float(np.max((ke / np.maximum(ie, 1e-30))[alive]))
            if steady_state_mm is not None and done * dt >= total - 0.5 * dt:
                remaining = distance_to_rest.estimate()
                if remaining is not None:
                    at_rest = np.all(remaining < steady_state_mm) and np.all(ke < 1e-3 * np.maximum(ie, 1e-30))
                    settled_checks = settled_checks + 1 if at_rest else 0
                    if settled_checks >= 2:
                        message = (f"settled at t = {done * dt:.4g} s (estimated distance to rest "
                                   f"{remaining.max():.2g} mm < {steady_state_mm} mm); stopped "
                                   f"{n_steps - done} of {n_steps} steps early")
                        break
            if relaxation is not None:  # the models the device found converged at this sample
                moving = of_sets(control.active.read(sample_done), None)
                converged_now = (moving == 0) & (active == 1) & (flags[:, 0] == 0)
                converged_forces[converged_now] = history["plate_forces"][-1][converged_now]
            if np.any(moving != active):
                active[:] = moving
                stop_models()
            if not active.any():
                break
            still = np.count_nonzero(active)
            if still < B and still <= PACK_AT * B:
                pack()
        wp.synchronize_device(device)
        wall = time.perf_counter() - started
        if kept:  # packed: every set's results, the last models' with them
            keep_results(Selection(np.arange(B), B, device, positions=members))

        def result(name, array):
            """The device array ``array`` of the batch's results, of every set."""
            return (kept[name] if kept else array).numpy()

        displacement = result("displacement", u).reshape(N, n_sets, 3).transpose(1, 0, 2).astype(np.float64) / MM
        if scaled:  # the masses and stable steps as mass scaling left them
            mass, mass_growth = result("mass", scaling.mass_float64), result("growth", scaling.growth)
            mass_rescales, stable_step = result("rescales", scaling.rescales), result("stable", scaling.stable)
        if relaxation is not None:
            estimated_error, converged_at, lowest = (result(name, getattr(control.state, name))
                                                     for name in ("estimated_error", "converged_at", "lowest"))

    statuses, messages, steps = [status] * n_sets, [message] * n_sets, [done] * n_sets
    if relaxation is not None:
        ke_ie_end_of_loading = float("nan")  # fictitious masses: the energy criterion does not apply
        for b in range(n_sets):
            if status != "completed" or b in failed:
                continue
            if active[b]:
                statuses[b] = "not converged"
                messages[b] = (f"dynamic relaxation stopped after {done} iterations with an estimated error of "
                               f"{estimated_error[b]:.3g} mm (tolerance {relaxation.tolerance_mm} mm); raise "
                               "max_iterations or the tolerance")
            else:
                steps[b] = int(converged_at[b])
                rescaled = (f"; fictitious masses raised {mass_rescales[b]} time(s) as elements stiffened"
                            if mass_rescales[b] else "")
                messages[b] = (f"converged in {steps[b]} iterations, estimated error {estimated_error[b]:.3g} mm"
                               + rescaled)
    elif status == "completed" and ke_ie_end_of_loading > ke_ie_limit:
        statuses = ["energy criterion exceeded"] * n_sets
        messages = n_sets * [(f"kinetic/internal energy at the end of loading is {ke_ie_end_of_loading:.1%} "
                              f"(limit {ke_ie_limit:.0%}): the response is not quasi-static; load more slowly or "
                              "damp more")]
    for b, text in failed.items():  # whatever else happened, these models stopped on an inverted element
        statuses[b], messages[b] = "inverted elements", text
    if mass_scaling:
        ratio = mass.reshape(N, n_sets).sum(axis=0) / weight.reshape(N, n_sets).sum(axis=0)
        messages = [f"{m}; mass scaling: total mass x{r:.3g}, time step {dt:.3g} s" for m, r in zip(messages, ratio)]
    solutions = []
    for b in range(n_sets):
        hist = {"time": np.array(history["time"]),
                "kinetic": np.array([h[b] for h in history["kinetic"]]),
                "internal": np.array([h[b] for h in history["internal"]]),
                "stable_time_step": np.array([h[b] for h in history["stable_time_step"]]),
                "plate_forces": np.array([h[b] for h in history["plate_forces"]])}
        plate_forces = hist["plate_forces"][-1] if len(hist["time"]) else np.zeros((P, 3))
        if relaxation is not None and not active[b] and b not in failed:
            plate_forces = converged_forces[b]  # at rest on the plates the contact kernel sees no force
        solutions.append(Solution(
            displacement=displacement[b], plate_forces=plate_forces,
            status=statuses[b], message=messages[b], steps=steps[b], time_step=dt, wall_time=wall,
            ke_ie_at_end_of_loading=ke_ie_end_of_loading, history=hist,
            estimated_error_mm=float(estimated_error[b]), stable_time_step=float(stable_step[b]),
            plate_normals=np.array([p.normal for p in plate_sets[b]]).reshape(P, 3),
            lowest_eigenvalue=float(lowest[b]) if relaxation is not None and np.isfinite(lowest[b]) else float("nan"),
            shear_speed_squared=float(speed_squared[b] / mass_growth[b]) if relaxation is not None else float("nan")))
    return solutions
