"""One batched TLED solve on the device, as an object: :class:`BatchRun`.

:func:`BreastBiomechLib.solver.tled.solve_batch` checks its arguments into :class:`BatchOptions`,
then ``BatchRun(model, materials, plate_sets, device, options).run()``. The run's parts are its
methods, each over the run's state (:class:`StepState`, the per-model device arrays that packing
moves, and the kernels' structs):

- set-up on the host (:meth:`BatchRun._plan`: time step, masses, load times) and the upload
  (:meth:`_upload_materials`, :meth:`_upload_state`, :meth:`_upload_loads`,
  :meth:`_upload_constraints`, :meth:`_upload_plates`);
- the steps (:meth:`enqueue_steps`: CUDA graphs of :data:`STEP_GRAPH_PAIRS` pairs of steps);
- the sample (:meth:`enqueue_sample`, read back by :meth:`_read_sample`), after which the stop
  rules decide: :class:`~BreastBiomechLib.solver.relaxation.RelaxationControl` on the device in a
  relaxation, :class:`SettledStop` on the host in physical time;
- packing the batch down to its moving models (:meth:`pack`) and keeping the results of those
  that leave (:meth:`keep_results`);
- the solutions (:meth:`_solutions`).

Units: the device holds SI (m, N, kg, s); displacements come back in mm.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, fields
from typing import Callable

import numpy as np
import warp as wp

from BreastBiomechLib.solver import kernels as k
from BreastBiomechLib.solver.capture import graph_capture
from BreastBiomechLib.solver.geometry import MeshGeometry
from BreastBiomechLib.solver.host_setup import (anp_mode, anp_slots, constraint_load_shapes, critical_time_step,
                                                element_lanes, material_table, merged_constraints, plate_pose,
                                                plate_sets_of_batch, relaxation_load_iterations, stress_noise_floor_mm,
                                                wave_modulus, wave_speed_ratio)
from BreastBiomechLib.solver.materials import ElementMaterials
from BreastBiomechLib.solver.memory import SolveSize, check_fits
from BreastBiomechLib.solver.model import LOAD_SHAPES, Model, Plate
from BreastBiomechLib.solver.packing import Selection
from BreastBiomechLib.solver.readback import HostCopy
from BreastBiomechLib.solver.relaxation import MM, QUOTIENT_WINDOW, DistanceToRest, RelaxationControl
from BreastBiomechLib.solver.settings import DynamicRelaxation
from BreastBiomechLib.solver.solution import Solution
from BreastBiomechLib.solver.stability import MassScaling, StableStepMonitor
from BreastBiomechLib.solver.warm import WarmStart, ramp_iterations, start_time, started_plates

ELEMENT_FORCES_BLOCK = 128  # threads per block of the element_forces kernels (see internal_force)
# pairs of steps per CUDA graph: each graph launch costs the GPU about 1.4 us of its own, 0.7 us a
# step in graphs of two steps and 0.15 us in graphs of ten (160k tets, H200, docs/benchmarks.md)
STEP_GRAPH_PAIRS = 5
# a batch is packed down to its models still moving once they are this fraction of it or fewer (see
# :mod:`packing`): a batch of 16 packs four times at most, and a fit's solves took 42.5 s packed at
# half, 43.4 at three quarters and 44.1 at every stop (H200, docs/benchmarks.md)
PACK_AT = 0.5
SPRING_PA_PER_MM_MM2_TO_N_PER_M = 1e-3  # (Pa/mm) x mm^2 = 1e3 N/m^3 x 1e-6 m^2
F32 = np.float32


@dataclass(frozen=True)
class BatchOptions:
    """How :func:`~BreastBiomechLib.solver.tled.solve_batch` solves (its keywords, checked):
    dynamic ``relaxation`` or physical time (``steady_state_mm``, ``mass_scaling``), the start
    (``initial_displacement`` mm or a ``warm_start``), sampling, the energy limit, progress and a
    memory cap. See ``solve_batch`` for each."""

    relaxation: DynamicRelaxation | None = None
    warm_start: WarmStart | None = None
    initial_displacement: np.ndarray | None = None
    sample_every: int = 200
    ke_ie_limit: float = 0.05
    steady_state_mm: float | None = None
    mass_scaling: bool = False
    progress: Callable[[float], bool | None] | None = None
    memory_limit_bytes: int | None = None

    def __post_init__(self) -> None:
        if self.warm_start is not None and (self.relaxation is None or self.initial_displacement is not None):
            raise ValueError("a warm start is a start of dynamic relaxation: give a relaxation and no "
                             "initial_displacement")
        if self.steady_state_mm is not None and (self.relaxation is not None or self.steady_state_mm <= 0):
            raise ValueError("steady_state_mm is a positive distance (mm) for physical-time solves; dynamic "
                             "relaxation has its own tolerance")
        if self.mass_scaling and self.relaxation is not None:
            raise ValueError("mass_scaling is an option of physical-time solves; dynamic relaxation always "
                             "scales masses")

    @property
    def scaled(self) -> bool:
        """Whether element masses are scaled (a relaxation, or physical time with mass scaling)."""
        return self.mass_scaling or self.relaxation is not None


@dataclass
class StepState:
    """The per-model device arrays of a run that packing moves (models innermost, see
    :mod:`packing`), each with its entries per model; the relaxation's arrays are None in physical
    time. Displacements m, forces N, energies J."""

    u: wp.array  # displacement (m)
    low: wp.array  # its float32 rounding remainder
    du: wp.array  # the last increment
    scratch: wp.array  # u_(n-1) while a sample computes the energy
    forces: wp.array  # internal forces, component planes (3, B N)
    anp_sums: wp.array
    anp_tmp: wp.array  # the ANP sums of a probe (diagnostics)
    inverted: wp.array = None  # per model: count, first element, its step, frozen
    no_flags: wp.array = None  # a probe's flags, never read
    plate_force: wp.array = None  # model b's plate p at 3 (b P + p)
    visco_state: wp.array = None  # K Prony terms per element and model
    kinetic: wp.array = None
    internal: wp.array = None
    f_curr: wp.array = None  # relaxation: forces at u
    f_last: wp.array = None  # ... at the Rayleigh quotient's reference state
    u_last: wp.array = None  # ... that reference state
    stiffness: wp.array = None  # ... the quotient's terms
    inertia: wp.array = None

    def take(self, staying: Selection, widths: dict[str, int]) -> None:
        """Every array replaced by its ``staying`` models', one at a time (each old array freed as
        its new one replaces it); ``widths``: entries per model of the arrays not one."""
        for f in fields(self):
            array = getattr(self, f.name)
            if array is not None:
                setattr(self, f.name, staying.take(array, widths.get(f.name, 1)))


class SettledStop:
    """Physical time's early stop (``steady_state_mm``): after the end of loading, when the
    estimated distance still to travel (:class:`DistanceToRest`) is below ``steady_state_mm`` at
    two samples in a row and KE/IE is below 1e-3 (KE/IE alone would stop too early: slow
    overdamped modes such as sliding on the chest wall carry almost no kinetic energy)."""

    def __init__(self, steady_state_mm: float) -> None:
        self.steady_state_mm = steady_state_mm
        self.checks = 0  # samples in a row at rest

    def settled(self, remaining: np.ndarray | None, ke: np.ndarray, ie: np.ndarray) -> bool:
        """Whether the models are at rest, given the estimated distances ``remaining`` (mm, None
        before an estimate exists) and energies (J) at this sample."""
        if remaining is None:
            return False
        at_rest = np.all(remaining < self.steady_state_mm) and np.all(ke < 1e-3 * np.maximum(ie, 1e-30))
        self.checks = self.checks + 1 if at_rest else 0
        return self.checks >= 2


def step_too_large(t: float, stable: float, dt: float) -> str:
    """The message of a step over the stable step ``stable`` (s) found at time ``t`` (s)."""
    return (f"at t = {t:.4g} s the model's stable time step is at most {stable:.3g} s, below the step used "
            f"({dt:.3g} s): the solve would diverge. Lower the safety factor or set a smaller time_step")


def interleaved(per_model: list) -> np.ndarray:
    """(B, M, ...) values of the B models as the kernels hold them: element e of model b at e*B + b."""
    first = np.shape(per_model[0])
    return np.stack(per_model, axis=1).reshape((first[0] * len(per_model),) + first[1:])


def device_array(values, dtype) -> wp.array:
    """``values`` on the current device as float32 (int32 for ``int``) of warp type ``dtype``."""
    return wp.array(np.ascontiguousarray(values, dtype=np.int32 if dtype is int else F32), dtype=dtype)


class BatchRun:
    """The solve of B variants of ``model`` (``materials[b]``; the plates moved by
    ``plate_displacements[b]`` or replaced by ``plates[b]``, see :func:`plate_sets_of_batch`) on
    ``device`` with ``options``, in the model's own numbering; ``element_ids[e]``: the name of
    element e in messages (None: e). Made on the host and uploaded in the constructor;
    :meth:`run` steps, samples and stops, and returns one :class:`Solution` per variant."""

    def __init__(self, model: Model, materials: list[ElementMaterials], device, options: BatchOptions,
                 plate_displacements: list | None = None, plates: list[list[Plate]] | None = None,
                 element_ids: np.ndarray | None = None) -> None:
        self.model, self.device, self.options, self.element_ids = model, device, options, element_ids
        self.relaxation = options.relaxation
        self.scaled = options.scaled
        # B: the models of the batch as the device holds them, n_sets as given; B falls where a
        # relaxation packs the batch down to its moving models (``members``: the sets they are)
        self.B, self.N, self.M = len(materials), len(model.mesh.nodes), len(model.mesh.tets)
        self.n_sets = self.B
        if self.B == 0:
            raise ValueError("solve_batch needs at least one material set")
        for mat in materials:
            if len(mat.mu) != self.M:
                raise ValueError(f"a material set has {len(mat.mu)} elements, the mesh has {self.M}")
        self.materials = [mat.long_term() for mat in materials] if self.relaxation is not None else materials
        self.plate_sets = plate_sets_of_batch(model, self.B, plate_displacements, plates)
        self.P = len(model.loading.plates)
        self._plan()
        with wp.ScopedDevice(device):
            self._upload_materials()
            self._upload_state()
            self._upload_loads()
            self._upload_constraints()
            self._upload_plates()
            self._prepare_control()

    # -- set-up ------------------------------------------------------------------------------

    def _plan(self) -> None:
        """The host's decisions before any upload: geometry, ANP slots, the memory check, the time
        step and masses, each model's load time and the step count."""
        model, materials, relaxation, B = self.model, self.materials, self.relaxation, self.B
        geometry = MeshGeometry.of(model.mesh.nodes, model.mesh.tets)  # computed once per mesh
        self.geometry, self.length = geometry, geometry.length
        self.slots, self.slot_volume = anp_slots(geometry.tets, materials, geometry.vol, model.anp_across_materials)
        self.S = len(self.slot_volume)
        self.K = max(m.prony_terms for m in materials)  # visco: Prony terms per element (padded with g = 0)
        check_fits(SolveSize(B, self.N, self.M, self.S, self.K,
                             sum(len(p.slave_nodes) for p in model.loading.plates), self.P), self.device,
                   self.options.memory_limit_bytes)
        length = self.length
        if self.scaled:  # mass scaling: every element's stable step becomes dt / safety
            dt = model.safety * float(np.median(length / np.sqrt(wave_modulus(materials[0]) / materials[0].density)))
            densities = [wave_modulus(mat) * (dt / (model.safety * length)) ** 2 for mat in materials]
            if relaxation is None:  # physical time: only add mass, where elements are below the step
                densities = [np.maximum(rho, mat.density) for rho, mat in zip(densities, materials)]
        else:
            densities = [mat.density for mat in materials]
            dt = model.time_step or model.safety * critical_time_step(model, materials, length)
        self.dt = dt
        if relaxation is None:
            self.totals = np.full(B, model.loading.total_time)
            self.n_steps = int(math.ceil((model.loading.total_time + model.loading.settle_time) / dt))
            self.sample_every = self.options.sample_every
        else:  # fictitious time: each model loads as slowly as its own materials and travel need
            load_iterations = relaxation_load_iterations(model, materials, self.plate_sets, relaxation, length)
            self.totals = load_iterations * dt
            self.n_steps = max(relaxation.max_iterations, 2 * int(load_iterations.max()))
            self.cold_load_time = self.totals  # sets the damping before the first update, warm or cold
            warm_start = self.options.warm_start
            if warm_start is not None:
                self.plate_sets = started_plates(model, warm_start, self.plate_sets)
                ratios = [wave_speed_ratio(m) for m in materials]
                self.totals = start_time(ramp_iterations(relaxation, self.plate_sets, ratios, float(np.median(length)),
                                                         model.safety), dt)
            # the scale of each model's lowest eigenvalue: mean mu / rho over the volume (m^2/s^2)
            vol = geometry.vol
            self.speed_squared = np.array([float(np.sum(vol * mat.mu / rho) / np.sum(vol))
                                           for mat, rho in zip(materials, densities)])
            self.noise_floor = stress_noise_floor_mm(materials, length)
            self.sample_every = relaxation.update_every
        self.total = float(self.totals.max())  # the batch's loading ends with its slowest model's
        # nodal masses (kg) of the B models, models innermost (node a of model b at a*B + b): a quarter
        # of each element's mass at its nodes
        self.mass = geometry.lumped(densities)
        self.weight = geometry.lumped([m.density for m in materials])  # physical masses: gravity acts on these
        if np.any(self.mass <= 0):
            raise ValueError("some nodes belong to no element (zero mass); remove unused nodes")

    def _upload_materials(self) -> None:
        """Mesh, ANP slots, the materials' table and the Prony terms on the device."""
        g, materials, K, dt = self.geometry, self.materials, self.K, self.dt
        self.d_tets = wp.array(g.tets, dtype=int)
        self.d_dhdx = wp.array(g.dhdx.astype(F32), dtype=wp.vec3)
        self.d_vol = device_array(g.vol, float)
        # one material (or ANP across materials): the slots are the nodes, and the kernels' reads of
        # both fall on one array (cached after the first)
        self.slots_are_nodes = bool(np.array_equal(self.slots, g.tets))
        self.d_slots = self.d_tets if self.slots_are_nodes else wp.array(self.slots, dtype=int)
        self.d_slotvol = device_array(self.slot_volume, float)
        self.d_materials = material_table(materials)
        # visco: K Prony terms per element (padded with g = 0), decay exp(-dt / tau) per step
        prony_g = interleaved([np.pad(m.prony_g, ((0, 0), (0, K - m.prony_terms))) for m in materials])
        prony_tau = interleaved([np.pad(m.prony_tau, ((0, 0), (0, K - m.prony_terms)), constant_values=1.0)
                                 for m in materials])
        self.d_prony_g = device_array(prony_g.reshape(-1) if K else np.zeros(1), float)
        self.d_prony_decay = device_array(np.exp(-dt / prony_tau).reshape(-1) if K else np.zeros(1), float)
        self.anp = anp_mode(self.model)
        self.formulation = k.element_kernels(self.anp, K > 0, self.slots_are_nodes)

    def _upload_state(self) -> None:
        """The state (displacement, increments, forces, flags, energies) at its start."""
        model, options, B, N, P = self.model, self.options, self.B, self.N, self.P
        initial = options.initial_displacement
        if model.prestate is not None:  # at rest in the pre-stressed state
            initial = model.prestate.displacement
        if options.warm_start is not None:
            initial = options.warm_start.displacement
        u0 = np.zeros((B * N, 3)) if initial is None else np.repeat(
            np.asarray(initial, float).reshape(N, 3) * MM, B, axis=0)
        # the state: displacement u (m), its float32 rounding remainder and the last increment
        self.state = StepState(
            u=device_array(u0, wp.vec3), low=wp.zeros(B * N, dtype=wp.vec3), du=wp.zeros(B * N, dtype=wp.vec3),
            scratch=wp.zeros(B * N, dtype=wp.vec3), forces=wp.zeros((3, B * N), dtype=float),
            anp_sums=wp.zeros(B * self.S, dtype=float), anp_tmp=wp.zeros(B * self.S, dtype=float),
            inverted=wp.zeros(4 * B, dtype=int), no_flags=wp.zeros(4 * B, dtype=int),
            plate_force=wp.zeros(max(3 * B * P, 1), dtype=float),
            visco_state=wp.zeros(max(B * self.M * self.K, 1), dtype=wp.mat33),
            kinetic=wp.zeros(B, dtype=float), internal=wp.zeros(B, dtype=float))
        self.clock = wp.zeros(2, dtype=int)  # the step: [as the element kernel reads it, as the node kernel does]
        self.probe_clock = wp.zeros(2, dtype=int)
        self.active = np.ones(self.n_sets, np.int32)  # the sets moving as of the last sample the host has read
        self.members = np.arange(self.n_sets)  # the set of each model of the batch as packed
        self.every_model = device_array(self.model_list(np.ones(B)), int)
        self.d_moving = device_array(self.model_list(self.active), int)  # the models the steps compute

    def _upload_loads(self) -> None:
        """Masses, gravity, damping and load times (:class:`kernels.NodeLoads`)."""
        model, B, relaxation, warm_start = self.model, self.B, self.relaxation, self.options.warm_start
        self.d_mass = device_array(self.mass, float)
        # gravity acts on the physical masses, also where dynamic relaxation scales them
        # with a pre-stressed reference state its gravity acts from the start, changing to the
        # loading's gravity over the load
        self.start_gravity = np.zeros(3) if model.prestate is None else model.prestate.gravity
        self.d_body_start = device_array(self.weight[:, None] * self.start_gravity, wp.vec3)
        self.d_body_force = device_array(self.weight[:, None] * (model.loading.gravity - self.start_gravity), wp.vec3)
        # dynamic relaxation starts critically damped for a mode of period ~ the loading time
        damping = np.full(B, model.damping) if relaxation is None else 4.0 * np.pi / self.cold_load_time
        # a warm start's damping never exceeds its start's lowest mode critical damping: the first
        # Rayleigh quotients after it measure the start's local misfit (high modes), not the lowest
        # mode, and would overdamp the approach (and mislead the distance estimate)
        self.damping_cap = np.full(B, np.inf)
        if warm_start is not None and np.isfinite(warm_start.lowest_eigenvalue):
            self.damping_cap = warm_start.critical_damping(self.speed_squared)
            damping = np.minimum(damping, self.damping_cap)
        self.damping = damping
        loads = self.loads = k.NodeLoads()
        loads.mass, loads.body_start, loads.body_force = self.d_mass, self.d_body_start, self.d_body_force
        loads.damping, loads.t_total = device_array(damping, float), device_array(self.totals, float)
        loads.load_shape, loads.dt = LOAD_SHAPES.index(model.loading.load_shape), float(self.dt)

    def _upload_constraints(self) -> None:
        """Prescribed components, sliding supports and support springs (:class:`kernels.NodeConstraints`)."""
        model, N, B = self.model, self.N, self.B
        c_nodes, c_mask, c_vals = merged_constraints(model)
        n_con = len(c_nodes)
        self.d_cnodes = device_array(c_nodes, int)
        self.d_cmask = device_array(c_mask.astype(F32), wp.vec3)
        constraints = self.constraints = k.NodeConstraints()
        row_of_node = np.full(N, -1, np.int32)
        row_of_node[c_nodes] = np.arange(n_con)
        constraints.constrained = device_array(row_of_node, int)
        constraints.mask = self.d_cmask if n_con else device_array(np.zeros((1, 3)), wp.vec3)
        constraints.shapes = wp.array(constraint_load_shapes(model, c_nodes).reshape(-1, 3) if n_con
                                      else np.zeros((1, 3), np.int32), dtype=wp.vec3i)
        constraints.value = device_array(np.repeat(c_vals * MM, B, axis=0) if n_con else np.zeros((1, 3)), wp.vec3)
        constraints.n_constrained = n_con

        # surface supports: springs (with the internal forces) and, sliding, the normal projection
        self.d_supports = []
        sliding = [s for s in model.loading.supports if s.mode == "sliding" and len(s.nodes)]
        slide = np.full((N, max(len(sliding), 1)), -1, np.int32)
        offset = 0
        for column, support in enumerate(sliding):
            slide[support.nodes, column] = offset + np.arange(len(support.nodes))
            offset += len(support.nodes)
        constraints.slide = wp.array(slide, dtype=int)
        constraints.n_sliding = len(sliding)
        constraints.slide_normals = device_array(np.concatenate([s.normals for s in sliding]) if sliding
                                                 else np.zeros((1, 3)), wp.vec3)
        self.sliding = bool(sliding)
        for support in model.loading.supports:
            if (support.normal_stiffness > 0 or support.tangential_stiffness > 0) and len(support.nodes):
                spring = np.stack([support.normal_stiffness * support.areas,
                                   support.tangential_stiffness * support.areas],
                                  axis=1) * SPRING_PA_PER_MM_MM2_TO_N_PER_M
                self.d_supports.append((len(support.nodes), device_array(support.nodes, int),
                                        device_array(support.normals, wp.vec3), device_array(spring, wp.vec2)))

    def _upload_plates(self) -> None:
        """The plates' poses, travel and friction per model (model b's plate p at b * P + p); a
        node may touch several plates, in turn; friction state per contact slot and model
        (:class:`kernels.PlateContact`); the node kernel for this loading."""
        model, N, B, P = self.model, self.N, self.B, self.P
        plates = self.plates = k.PlateContact()
        contact_slot = np.full((N, max(P, 1)), -1, np.int32)
        n_slots = 0
        self.plate_slots = []  # plate p's slots: (first, count)
        for p, plate in enumerate(model.loading.plates):
            contact_slot[plate.slave_nodes, p] = n_slots + np.arange(len(plate.slave_nodes))
            self.plate_slots.append((n_slots, len(plate.slave_nodes)))
            n_slots += len(plate.slave_nodes)
        every_plate = [p for ps in self.plate_sets for p in ps]
        plates.slot = wp.array(contact_slot, dtype=int)
        plates.n_plates = P
        plates.x0 = device_array(self.geometry.nodes_m, wp.vec3)
        plates.pose = wp.array([plate_pose(p) for p in every_plate] or [k.PlatePose()], dtype=k.PlatePose,
                               device=self.device)
        plates.anchor = wp.zeros(max(B * n_slots, 1), dtype=wp.vec3)
        plates.touching = wp.zeros(max(B * n_slots, 1), dtype=int)
        plates.force = wp.zeros(max(B * n_slots, 1), dtype=wp.vec3)
        self.node_update = k.node_kernel(bool(np.any(self.start_gravity) or np.any(model.loading.gravity)),
                                         any(p.friction > 0 for p in every_plate), self.sliding)

    def _prepare_control(self) -> None:
        """The sample's helpers: the relaxation's quotient terms and decisions, the stable-step
        monitor, mass scaling, the distance to rest and the host's copies of the sample."""
        B, N, s = self.B, self.N, self.state
        self.distance_to_rest = DistanceToRest(s.u, B)
        if self.relaxation is not None:
            # the state and forces of a reference renewed every QUOTIENT_WINDOW updates: the
            # Rayleigh quotient of the change over one to QUOTIENT_WINDOW whole update intervals
            # (single-step changes near rest are float32 noise, whose quotient grows towards the
            # highest modes and overdamps the slow ones; over longer windows a slow mode's motion
            # adds up while faster ones' does not)
            s.f_curr, s.f_last = wp.zeros((3, B * N), dtype=float), wp.zeros((3, B * N), dtype=float)
            s.u_last = wp.clone(s.u)
            self.probe_force(s.u_last, s.f_last)
            s.stiffness, s.inertia = wp.zeros(B, dtype=float), wp.zeros(B, dtype=float)
            self.control = RelaxationControl(self.totals, self.damping, self.loads.damping, self.damping_cap,
                                             self.noise_floor, self.dt, self.relaxation.tolerance_mm,
                                             self.options.warm_start is not None)
        self.monitor = StableStepMonitor(self.probe_force, self.d_mass, B, N, 1e-3 * float(np.median(self.length)),
                                         self.d_cnodes, self.d_cmask)
        # mass scaling: where the model is stiffer than the element estimate (or got stiffer as it
        # deformed) its fictitious masses grow so that the step stays stable (see MassScaling)
        self.scaling = MassScaling(self.d_mass, self.mass, self.dt, B) if self.scaled else None
        # what the host reads of each sample, copied back together (see :mod:`readback`)
        self.sampled = {name: HostCopy(getattr(s, name)) for name in ("kinetic", "internal", "plate_force",
                                                                        "inverted")}
        self.graphs = {}  # on CUDA: (pairs of steps, count of moving models) -> a graph of those steps
        # on CUDA one graph launch and one wait per sample instead of some thirty of each; each
        # kind of sample captured when first needed, so the host captures while the GPU steps
        self.sample_graphs = {}
        self.kept = {}  # the results of sets packed out of the batch (see keep_results)
        self.latest = {}  # of_sets' last values of every set, by name

    def model_list(self, flags) -> np.ndarray:
        """The kernels' list of models (see :mod:`kernels`): the flagged models, then padding."""
        chosen = np.flatnonzero(flags)
        listing = np.zeros(self.B, np.int32)
        listing[:len(chosen)] = chosen
        return listing

    # -- the steps ---------------------------------------------------------------------------

    def internal_force(self, state, out, sums_buffer, flags, models=None, width=None, update_state=0,
                       cleared=False, step_clock=None) -> None:
        """Internal nodal forces of ``state`` into ``out`` (ANP sums in ``sums_buffer``) for the
        first ``width`` models of the list ``models`` (the others' stay zero; None: every model of
        the batch); ``update_state`` advances the visco state variables by one step; ``cleared``:
        ``out`` and ``sums_buffer`` are zero already (the step kernels clear them). A step passes
        its clock (see ``kernels.element_kernels``' element_forces); a probe leaves it alone."""
        B, M, formulation = self.B, self.M, self.formulation
        if models is None:
            models, width = self.every_model, B
        if not cleared:
            out.zero_()
            sums_buffer.zero_()
        # a thread per element and model, or (lanes < width) per element and several models
        lanes = element_lanes(width)
        shared = [lanes] if lanes < width else []
        if self.anp != k.ANP_OFF:
            wp.launch(formulation.nodal_pressure_shared if shared else formulation.nodal_pressure, lanes * M,
                      [state, self.d_tets, self.d_slots, self.d_dhdx, self.d_vol, self.d_materials, B, models, width,
                       sums_buffer] + shared)
        # blocks of 128 threads: at its register count the kernel fits 7 of them on an SM
        # against 3 of 256, so a lone 160k-tet model's elements take 1.35 waves, not 1.58
        # (4.5 % less time, H200, docs/benchmarks.md)
        wp.launch(formulation.element_forces_shared if shared else formulation.element_forces, lanes * M,
                  [state, self.d_tets, self.d_dhdx, self.d_vol, self.d_materials, self.d_slots, sums_buffer,
                   self.d_slotvol, self.K, self.d_prony_g, self.d_prony_decay, self.state.visco_state, update_state, B,
                   self.probe_clock if step_clock is None else step_clock, models, width, out, flags] + shared,
                  block_dim=ELEMENT_FORCES_BLOCK)
        for n_sup, d_snodes, d_snormals, d_sstiff in self.d_supports:
            wp.launch(k.support_springs, width * n_sup, [state, d_snodes, d_snormals, d_sstiff, B, models, width,
                                                         out])

    def probe_force(self, state, out) -> None:
        """Internal forces for diagnostics: no visco update, inverted elements not recorded."""
        self.internal_force(state, out, self.state.anp_tmp, self.state.no_flags)

    def one_step(self, width: int) -> None:
        """One step of the ``width`` moving models: converged models stand still, and their
        threads are not launched."""
        s = self.state
        self.internal_force(s.u, s.forces, s.anp_sums, s.inverted, self.d_moving, width, update_state=1,
                            cleared=True, step_clock=self.clock)
        wp.launch(self.node_update, width * self.N, [s.u, s.low, s.du, s.forces, s.anp_sums, self.loads,
                                                     self.constraints, self.plates, self.d_moving, width, self.B,
                                                     self.clock, s.inverted])

    def enqueue_steps(self, pairs: int) -> None:
        """``pairs`` pairs of steps of the models the host knows to be moving: on CUDA graphs of
        :data:`STEP_GRAPH_PAIRS` pairs, then graphs of one pair for the rest. The threads launched
        per element (node) are the moving models' count (it only falls, so a batch captures one
        graph per count it passes through)."""
        width = int(np.count_nonzero(self.active))
        if not self.device.is_cuda:
            for _ in range(2 * pairs):
                self.one_step(width)
            return
        groups, rest = divmod(pairs, STEP_GRAPH_PAIRS)
        for size, count in ((STEP_GRAPH_PAIRS, groups), (1, rest)):
            if count and (size, width) not in self.graphs:
                with graph_capture() as capture:
                    for _ in range(2 * size):
                        self.one_step(width)
                self.graphs[size, width] = capture.graph
            for _ in range(count):
                wp.capture_launch(self.graphs[size, width])

    # -- the sample --------------------------------------------------------------------------

    def sample(self, renew: bool = True) -> None:
        """The device work of a sample, before anything is read back: energies, the forces at u
        (relaxation), a power iteration, the relaxation's Rayleigh-quotient terms (and, ``renew``,
        u and its forces as their next reference), the displacement change since the last
        sample, the plates' forces in the last step, mass scaling and the relaxation's decisions."""
        s, B, N, M, P, relaxation = self.state, self.B, self.N, self.M, self.P, self.relaxation
        s.kinetic.zero_()
        s.internal.zero_()
        # kinetic energy at the half step n - 1/2 and the internal energy averaged over u_n and
        # u_{n-1}: the pair the central-difference scheme conserves to second order
        k.reduction_launch(k.energies, B, N, [s.du, self.d_mass, float(self.dt), N, s.kinetic])
        wp.launch(k.perturbed, B * N, [s.u, s.du, -1.0, s.scratch])  # u_(n-1)
        for state in (s.u, s.scratch):
            k.reduction_launch(k.internal_energy, B, M, [state, self.d_tets, self.d_dhdx, self.d_vol, self.d_materials,
                                                         N, M, s.internal])
        if relaxation is not None:  # the relaxation update needs the same forces
            self.probe_force(s.u, s.f_curr)
        self.monitor.advance(s.u, base_force=s.f_curr if relaxation is not None else None)
        if relaxation is not None:
            for a in (s.stiffness, s.inertia):
                a.zero_()
            k.reduction_launch(k.relaxation_terms, B, N, [s.u, s.u_last, s.f_curr, s.f_last, self.d_mass, N,
                                                          s.stiffness, s.inertia])
            if renew:
                wp.copy(s.u_last, s.u)
                wp.copy(s.f_last, s.f_curr)
        self.distance_to_rest.measure(s.u)
        s.plate_force.zero_()
        for p, (first, count) in enumerate(self.plate_slots):
            k.reduction_launch(k.plate_forces, B, count, [self.plates.force, B, first, count, p, P, s.inverted,
                                                          s.plate_force])
        if self.scaled:
            self.scaling.apply(self.monitor, s.inverted)
        if relaxation is not None:
            self.control.update(self.distance_to_rest, s.kinetic, s.internal, s.stiffness, s.inertia, s.inverted,
                                self.clock)
        for copy in self.sampled.values():
            copy.refresh()

    def enqueue_sample(self, renew: bool) -> None:
        """A sample's device work (see :meth:`sample`): on CUDA its graph's launch."""
        if not self.device.is_cuda:
            self.sample(renew)
            return
        if renew not in self.sample_graphs:
            with graph_capture() as capture:
                self.sample(renew)
            self.sample_graphs[renew] = capture.graph
        wp.capture_launch(self.sample_graphs[renew])

    def of_sets(self, values: np.ndarray, name: str | None) -> np.ndarray:
        """``values`` of the batch as packed, in their sets' places: a set packed out keeps its
        latest value of that ``name`` (None: zero, and nothing kept)."""
        out = np.zeros((self.n_sets,) + values.shape[1:], values.dtype)
        if name in self.latest:
            out[:] = self.latest[name]
        out[self.members] = values
        if name is not None:
            self.latest[name] = out
        return out

    # -- packing -----------------------------------------------------------------------------

    def keep_results(self, leaving: Selection) -> None:
        """Device copies, into arrays of every set, of what the end of the solve reads of the
        selected models ``leaving`` of the batch as packed (positioned as their sets):
        displacement, relaxation outcome, masses."""
        per_model_arrays = [("displacement", self.state.u)]
        if self.relaxation is not None:
            per_model_arrays += [(name, getattr(self.control.state, name))
                                 for name in ("converged_at", "estimated_error", "lowest")]
        if self.scaled:
            per_model_arrays += [("mass", self.scaling.mass_float64), ("growth", self.scaling.growth),
                                 ("stable", self.scaling.stable), ("rescales", self.scaling.rescales)]
        for name, array in per_model_arrays:
            if name not in self.kept:
                shape = array.shape[:-1] + (array.shape[-1] // self.B * self.n_sets,)
                self.kept[name] = wp.zeros(shape, dtype=array.dtype)
            leaving.put(array, self.kept[name], self.n_sets)

    def stop_models(self) -> None:
        """The models no longer ``active`` out of the steps' list (the steps leave them alone
        already: they are frozen, see :mod:`relaxation`)."""
        self.d_moving.assign(self.model_list(self.active[self.members]))

    def pack(self) -> None:
        """The batch packed down to its models still ``active``, in their order (device work,
        after the steps already enqueued: see :mod:`packing`); the others' results kept
        (:meth:`keep_results`). The old arrays and graphs go: CUDA frees them in the stream's
        order, after the work enqueued on them."""
        B, P, K, members, device = self.B, self.P, self.K, self.members, self.device
        stays = self.active[members] == 1
        staying = Selection(np.flatnonzero(stays), B, device)
        leaving = np.flatnonzero(~stays)
        self.keep_results(Selection(leaving, B, device, positions=members[leaving]))
        for name in ("kinetic", "plate_forces"):  # at rest, as a frozen model in the batch: no motion, no contact
            self.latest[name] = self.latest[name].copy()  # (the history holds the sample's own)
            self.latest[name][members[leaving]] = 0.0
        self.graphs.clear()
        self.sample_graphs.clear()

        # one array at a time, each old one freed as its new one replaces it: the packing needs
        # no more memory than the batch plus its largest array's share of the models kept
        take = staying.take
        self.state.take(staying, {"inverted": 4, "no_flags": 4, "plate_force": 3 * P, "visco_state": K})
        table = k.MaterialTable()
        table.row, table.values = self.d_materials.row, take(self.d_materials.values)
        self.d_materials = table
        self.d_prony_g = take(self.d_prony_g, K)
        self.d_prony_decay = take(self.d_prony_decay, K)
        loads = self.loads
        self.d_mass = loads.mass = take(self.d_mass)
        loads.damping = take(loads.damping)
        loads.t_total = take(loads.t_total)
        self.d_body_start = loads.body_start = take(self.d_body_start)
        self.d_body_force = loads.body_force = take(self.d_body_force)
        self.constraints.value = take(self.constraints.value)
        plates = self.plates
        plates.pose = take(plates.pose, P)
        plates.anchor = take(plates.anchor)
        plates.touching = take(plates.touching)
        plates.force = take(plates.force)
        if self.relaxation is not None:
            self.control.keep(staying, loads.damping)
        self.distance_to_rest.keep(staying)
        self.monitor.keep(staying, self.d_mass)
        if self.scaling is not None:
            self.scaling.keep(staying, self.d_mass)
        self.members, self.B = members[staying.models], len(staying)
        self.every_model = device_array(self.model_list(np.ones(self.B)), int)
        self.d_moving = device_array(self.model_list(self.active[self.members]), int)
        for name in ("kinetic", "internal", "plate_force", "inverted"):
            self.sampled[name].follow(getattr(self.state, name))

    # -- the run -----------------------------------------------------------------------------

    def run(self) -> list[Solution]:
        """Step, sample and stop; the solutions of every set (see ``solve_batch``)."""
        with wp.ScopedDevice(self.device):
            self._start()
            while self.status == "completed" and self.done < self.n_steps:
                if not self._interval():
                    break
            wp.synchronize_device(self.device)
            self.wall = time.perf_counter() - self.started
            return self._solutions()

    def _start(self) -> None:
        """The loop's state and the first stable-step estimate; the wall time starts here."""
        B, P = self.B, self.P
        self.history = {"time": [], "kinetic": [], "internal": [], "plate_forces": [], "stable_time_step": []}
        self.status, self.message = "completed", "completed"
        self.ke_ie_end_of_loading = float("nan")
        self.chunk = max(2, self.sample_every - self.sample_every % 2)
        self.done = 0
        self.samples = 0
        # a warm start's damping is capped by its start's lowest mode (critically damped at most,
        # so no overdamped creep to mistake for rest): see DynamicRelaxation's docstring
        self.window = 1 if self.options.warm_start is not None else QUOTIENT_WINDOW
        self.converged_forces = np.zeros((B, P, 3))  # a relaxation's plate forces at the sample it converged
        steady = self.options.steady_state_mm
        self.settled_stop = SettledStop(steady) if steady is not None else None
        self.failed: dict[int, str] = {}  # models stopped by an inverted element: their message
        # a relaxation's decisions are the device's: after each sample the next steps (a quarter of
        # an interval) are enqueued before the host reads it, and run while it does
        self.lead = max(1, self.chunk // 8) if self.relaxation is not None else 0  # pairs of steps
        self.ahead = 0  # pairs of steps of the current interval enqueued before the last sample was read
        self.sample_done = wp.Event(self.device) if self.device.is_cuda else None  # after each sample's copies
        # the wall time spans the device's work and the host's control of it; the arrays above
        # (the power iteration's random start among them) are set-up, like the mesh's
        wp.synchronize_device(self.device)
        self.started = time.perf_counter()
        self.monitor.advance(self.state.u, iterations=20)
        if self.scaled:
            self.scaling.apply(self.monitor, self.state.inverted)
        # the host waits for the estimate only where the steps must be checked against it first
        self.stable_step = None if self.scaled else self.monitor.stable_step()
        if not self.scaled and self.dt > self.stable_step.min():
            self.status, self.message = "unstable", step_too_large(0.0, self.stable_step.min(), self.dt)

    def _pairs_after(self, after: int) -> int:
        """Pairs of steps of the sampling interval after step ``after``."""
        return min(self.chunk, self.n_steps - after + (self.n_steps - after) % 2) // 2

    def _interval(self) -> bool:
        """One sampling interval: its steps, the sample, the next steps enqueued ahead, and the
        host's reading of the sample (:meth:`_read_sample`); whether the run goes on."""
        pairs = self._pairs_after(self.done)
        self.enqueue_steps(pairs - self.ahead)
        self.done += 2 * pairs
        self.samples += 1
        self.enqueue_sample(self.relaxation is None or self.samples % self.window == 0)
        if self.sample_done is not None:
            wp.record_event(self.sample_done)
        self.ahead = min(self.lead, self._pairs_after(self.done))
        if self.ahead:
            self.enqueue_steps(self.ahead)
        return self._read_sample()

    def _read_sample(self) -> bool:
        """The host reads the sample: history, inverted elements, divergence, the stable step,
        progress and cancel, the stop rules; models that stopped leave the steps (and the batch
        is packed once few are left). Whether the run goes on."""
        dt, done, after, active, history = self.dt, self.done, self.sample_done, self.active, self.history
        ke = self.of_sets(self.sampled["kinetic"].read(after).astype(float), "kinetic")
        ie = self.of_sets(0.5 * self.sampled["internal"].read(after).astype(float), "internal")
        history["time"].append(done * dt)
        history["kinetic"].append(ke)
        history["internal"].append(ie)
        history["plate_forces"].append(self.of_sets(self.sampled["plate_force"].read(after)[: 3 * self.B * self.P]
                                                    .reshape(self.B, self.P, 3).astype(float), "plate_forces"))
        flags = self.of_sets(self.sampled["inverted"].read(after).reshape(self.B, 4), "flags")
        for b in np.flatnonzero((flags[:, 0] > 0) & (active == 1)):
            count, element, at = flags[b, :3]
            element = element if self.element_ids is None else int(self.element_ids[element])
            self.failed[int(b)] = (f"{count} element(s) inverted (J <= 0) at step {at} (t = {at * dt:.4g} s), first "
                                   f"element {element}; the displacement returned is that configuration. Reduce the "
                                   "load, refine the mesh there or check the constraints")
        # frozen by the kernels; the other models of the batch go on
        moving = np.where(flags[:, 0] > 0, 0, active)
        if not moving.any():
            active[:] = moving
            return False
        alive = np.array([b not in self.failed for b in range(self.n_sets)])
        if not np.all(np.isfinite(ke[alive])) or not np.all(np.isfinite(ie[alive])):
            self.status, self.message = "unstable", (f"the solution diverged by step {done + 2 * self.ahead}; reduce "
                                                     f"the time step (now {dt:.3g} s) or the safety factor")
            return False
        stable_step = self.of_sets(self.monitor.stable_step(after), "stable_time_step")
        stable_step[~alive] = np.inf  # a frozen model's step no longer matters
        self.stable_step = stable_step
        history["stable_time_step"].append(stable_step)
        if not self.scaled and dt > stable_step.min():
            self.status, self.message = "unstable", step_too_large(done * dt, stable_step.min(), dt)
            return False
        progress = self.options.progress
        if progress is not None and progress(done / self.n_steps) is False:
            self.status, self.message = ("cancelled", f"cancelled after {done + 2 * self.ahead} steps; the "
                                         "displacement returned is that state")
            return False
        loaded = done * dt >= self.total - 0.5 * dt
        if np.isnan(self.ke_ie_end_of_loading) and loaded:
            self.ke_ie_end_of_loading = float(np.max((ke / np.maximum(ie, 1e-30))[alive]))
        if self.settled_stop is not None and loaded:
            remaining = self.distance_to_rest.estimate()
            if self.settled_stop.settled(remaining, ke, ie):
                self.message = (f"settled at t = {done * dt:.4g} s (estimated distance to rest "
                                f"{remaining.max():.2g} mm < {self.settled_stop.steady_state_mm} mm); stopped "
                                f"{self.n_steps - done} of {self.n_steps} steps early")
                return False
        if self.relaxation is not None:  # the models the device found converged at this sample
            moving = self.of_sets(self.control.active.read(after), None)
            converged_now = (moving == 0) & (active == 1) & (flags[:, 0] == 0)
            self.converged_forces[converged_now] = history["plate_forces"][-1][converged_now]
        if np.any(moving != active):
            active[:] = moving
            self.stop_models()
        if not active.any():
            return False
        still = np.count_nonzero(active)
        if still < self.B and still <= PACK_AT * self.B:
            self.pack()
        return True

    # -- the results -------------------------------------------------------------------------

    def _solutions(self) -> list[Solution]:
        """One :class:`Solution` per set, read back (the sets packed out from what was kept)."""
        n_sets, N, P, relaxation = self.n_sets, self.N, self.P, self.relaxation
        if self.kept:  # packed: every set's results, the last models' with them
            self.keep_results(Selection(np.arange(self.B), self.B, self.device, positions=self.members))

        def result(name, array):
            """The device array ``array`` of the batch's results, of every set."""
            return (self.kept[name] if self.kept else array).numpy()

        displacement = result("displacement", self.state.u).reshape(N, n_sets, 3).transpose(1, 0, 2) \
            .astype(np.float64) / MM
        mass, stable_step = self.mass, self.stable_step
        if self.scaled:  # the masses and stable steps as mass scaling left them
            mass, mass_growth = result("mass", self.scaling.mass_float64), result("growth", self.scaling.growth)
            mass_rescales, stable_step = result("rescales", self.scaling.rescales), result("stable", self.scaling.stable)
        if relaxation is not None:
            estimated_error, converged_at, lowest = (result(name, getattr(self.control.state, name))
                                                     for name in ("estimated_error", "converged_at", "lowest"))
        else:
            estimated_error = np.full(n_sets, np.nan)

        status, message, done = self.status, self.message, self.done
        statuses, messages, steps = [status] * n_sets, [message] * n_sets, [done] * n_sets
        ke_ie_end_of_loading = self.ke_ie_end_of_loading
        if relaxation is not None:
            ke_ie_end_of_loading = float("nan")  # fictitious masses: the energy criterion does not apply
            for b in range(n_sets):
                if status != "completed" or b in self.failed:
                    continue
                if self.active[b]:
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
        elif status == "completed" and ke_ie_end_of_loading > self.options.ke_ie_limit:
            statuses = ["energy criterion exceeded"] * n_sets
            messages = n_sets * [(f"kinetic/internal energy at the end of loading is {ke_ie_end_of_loading:.1%} "
                                  f"(limit {self.options.ke_ie_limit:.0%}): the response is not quasi-static; load "
                                  "more slowly or damp more")]
        for b, text in self.failed.items():  # whatever else happened, these models stopped on an inverted element
            statuses[b], messages[b] = "inverted elements", text
        if self.options.mass_scaling:
            ratio = mass.reshape(N, n_sets).sum(axis=0) / self.weight.reshape(N, n_sets).sum(axis=0)
            messages = [f"{m}; mass scaling: total mass x{r:.3g}, time step {self.dt:.3g} s"
                        for m, r in zip(messages, ratio)]
        history = self.history
        solutions = []
        for b in range(n_sets):
            hist = {"time": np.array(history["time"]),
                    "kinetic": np.array([h[b] for h in history["kinetic"]]),
                    "internal": np.array([h[b] for h in history["internal"]]),
                    "stable_time_step": np.array([h[b] for h in history["stable_time_step"]]),
                    "plate_forces": np.array([h[b] for h in history["plate_forces"]])}
            plate_forces = hist["plate_forces"][-1] if len(hist["time"]) else np.zeros((P, 3))
            if relaxation is not None and not self.active[b] and b not in self.failed:
                plate_forces = self.converged_forces[b]  # at rest on the plates the contact kernel sees no force
            solutions.append(Solution(
                displacement=displacement[b], plate_forces=plate_forces,
                status=statuses[b], message=messages[b], steps=steps[b], time_step=self.dt, wall_time=self.wall,
                ke_ie_at_end_of_loading=ke_ie_end_of_loading, history=hist,
                estimated_error_mm=float(estimated_error[b]), stable_time_step=float(stable_step[b]),
                plate_normals=np.array([p.normal for p in self.plate_sets[b]]).reshape(P, 3),
                lowest_eigenvalue=(float(lowest[b]) if relaxation is not None and np.isfinite(lowest[b])
                                   else float("nan")),
                shear_speed_squared=(float(self.speed_squared[b] / mass_growth[b]) if relaxation is not None
                                     else float("nan"))))
        return solutions
