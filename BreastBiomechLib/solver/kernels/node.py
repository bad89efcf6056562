"""The node kernel (:func:`node_kernel`, ``advance_nodes``): the central-difference update with
mass-proportional damping, gravity, prescribed components, sliding supports and plate contact.
SI units.
"""

from __future__ import annotations

import functools
import inspect

import warp as wp

from BreastBiomechLib.solver.kernels.common import SPECIALISED, NodeState, force_at, listed, load_factor, set_component
from BreastBiomechLib.solver.kernels.contact import NodeConstraints, PlateContact, touch_plate

wp.set_module_options({"fast_math": True})  # as every module of this package (why: common.py)


@wp.struct
class NodeLoads:
    """What the step applies at the nodes besides the internal forces (SI units, LPS axes).

    External force per node ``body_start + load x body_force`` (N; gravity on the physical
    masses, see :func:`advance_nodes`); ``damping[b]`` model b's coefficient (1/s);
    ``t_total[b]`` the time (s) at which model b's load is full; ``load_shape`` the plates' and
    gravity's load curve (``LOAD_*``)."""
    mass: wp.array(dtype=float)
    body_start: wp.array(dtype=wp.vec3)
    body_force: wp.array(dtype=wp.vec3)
    damping: wp.array(dtype=float)
    t_total: wp.array(dtype=float)
    load_shape: int
    dt: float


# registers per thread the CUDA build of advance_nodes may use: nvcc gives it 53, which lets an SM
# hold 4 blocks of 256 threads (50 % occupancy); at 48 it holds 5. The kernel is bound by the latency
# of its reads (in a batch of 64 at 160k tets: 19 % of the DRAM bandwidth, 54 of every 67 cycles a
# warp waits on a load, Nsight Compute, H200), so more warps in flight hide more of it: batches of 64
# step 2.6 % faster, of 16 1.5 %, a lone 160k-tet model 0.7 %, 2M tets 0.7 % (H200,
# docs/benchmarks.md; at 40, with spills, batches 14 % slower). A warp without the option (1.17 has
# it) builds the kernel as before.
NODE_KERNEL_REGISTERS = 48


NODE_KERNEL_OPTIONS = ({"cuda_max_registers": NODE_KERNEL_REGISTERS}
                       if "cuda_max_registers" in inspect.signature(wp.kernel).parameters else {})


@functools.cache
def node_kernel(gravity: bool, friction: bool, sliding: bool) -> wp.Kernel:
    """:func:`advance_nodes` built for one kind of loading: body forces (``gravity``: the loads'
    ``body_start`` and ``body_force`` are read, else they are zero and not read), plate friction
    (``friction``: some plate of the batch has mu > 0, else every plate is frictionless) and
    sliding supports (``sliding``: ``constraints.n_sliding`` > 0), as compile-time constants (see
    :func:`element_kernels`): without them 821 static instructions and no spills against 1 183
    and 4; batches of 16 8 % faster, of 64 2 % (H200, docs/benchmarks.md). Each combination is
    compiled once, on its first launch."""

    @wp.kernel(name="advance_nodes", **SPECIALISED, **NODE_KERNEL_OPTIONS)
    def advance_nodes(u: wp.array(dtype=wp.vec3), low: wp.array(dtype=wp.vec3), du: wp.array(dtype=wp.vec3),
                      forces: wp.array2d(dtype=float), anp_sums: wp.array(dtype=float),
                      loads: NodeLoads, constraints: NodeConstraints, plates: PlateContact,
                      models: wp.array(dtype=int), n_listed: int, n_models: int, clock: wp.array(dtype=int),
                      inverted: wp.array(dtype=int)):
        """The node half of a step, one thread per node of each listed model (``models[:n_listed]``,
        see the module's docstring; the launch's size n_listed x nodes), everything a node's update
        needs in one launch, its state kept in registers (:class:`NodeState`) from its one read to
        its one write (at breast-model sizes a step is bound by latency, not by bandwidth):

        1. Seed eq. (15) in increment form: du_(n+1) = ((R - F) dt^2 / m + (1 - a dt/2) du_n) /
           (1 + a dt/2), u_(n+1) = u_n + du_(n+1), the same scheme as (m/dt^2 + a m/(2 dt)) u_(n+1) =
           R - F + 2m/dt^2 u_n - (m/dt^2 - a m/(2 dt)) u_(n-1) without its float32 cancellation, and
           u accumulated with compensation (Kahan summation, the remainder in ``low``). ``du`` holds
           the last increment (velocity x dt). The external force R is ``body_start + load x body_force`` (gravity on
           the physical mass; ``mass`` may be fictitious under mass scaling): the force already
           acting at the start (a pre-stressed, gravity-loaded reference state) and its change over
           the loading. A model not listed or frozen (converged) stands still; one with an inverted
           element stands still altogether.
        2. Sliding supports: the displacement, its increment and compensation lose their part along
           the node's surface normal.
        3. Prescribed components take load(t) x their final value, each component with its own load
           curve; their increment becomes the change from the previous step, their compensation zero
           (they win over sliding).
        4. Contact with each plate in turn (:func:`touch_plate`), the force through each contact
           node kept for :func:`plate_forces`.
        5. The internal force is cleared for the next step, a model in which an inverted element was
           found is frozen (``inverted[4b + 3]`` = 1, see :func:`element_forces`; by its node 0's
           thread; a relaxation freezes converged models with 2), and the step clock advances: this
           kernel reads the step from ``clock[1]`` (which :func:`element_forces` copies from
           ``clock[0]``) and writes ``clock[0]``, so no thread reads what another writes.

        Also clears the ANP sums, already used by this step's element forces."""
        with_friction = wp.static(int(friction))  # constants of this build (see node_kernel)
        tid = wp.tid()
        n_nodes = plates.slot.shape[0]
        j = tid
        while j < anp_sums.shape[0]:
            anp_sums[j] = 0.0
            j += n_listed * n_nodes
        step = clock[1]
        at = listed(models, n_listed, n_models, tid)
        a, b = at[0], at[1]  # the node and the model
        if a < 0 or a >= n_nodes:
            return
        i = a * n_models + b
        # every read that does not depend on another first (the model's inversion count and frozen
        # flag too: tested once the node's reads are on their way)
        count = inverted[4 * b]
        frozen = inverted[4 * b + 3]
        f = force_at(forces, i)
        x = NodeState()
        x.u = u[i]
        x.low = low[i]
        du_last = du[i]
        mass = loads.mass[i]
        external = wp.vec3(0.0)
        body_force = wp.vec3(0.0)
        if wp.static(gravity):
            external = loads.body_start[i]
            body_force = loads.body_force[i]
        damping = loads.damping[b]
        t_total = loads.t_total[b]
        k = constraints.constrained[a]
        forces[0, i] = 0.0
        forces[1, i] = 0.0
        forces[2, i] = 0.0
        # the clock advances only here, with the node's reads on their way: stored where the step
        # is read, it held every warp until that read had come back before any other was issued
        # (the store's wait on its operand applies to the threads it is predicated off for too);
        # batches of 64 step 9 % faster, of 16 3 %, a lone model 2.5-4.5 % (H200, docs/benchmarks.md)
        if tid == 0:
            clock[0] = step + 1
        if count != 0 or frozen != 0:
            if a == 0 and count != 0:
                inverted[4 * b + 3] = 1
            du[i] = wp.vec3(0.0)
            return
        t = float(step + 1) * loads.dt
        s = load_factor(t, t_total, loads.load_shape)
        external = external + s * body_force
        half = 0.5 * damping * loads.dt
        x.du = ((external - f) / mass * (loads.dt * loads.dt) + (1.0 - half) * du_last) / (1.0 + half)
        # u += du with the rounding error carried in low (Kahan summation): the displacement is
        # u + low to about 1e-14 m; plain float32 loses increments below half an ulp of u (1e-9 m
        # at 20 mm), so slow motion at small time steps would stall short of equilibrium
        y = x.du + x.low
        total = x.u + y
        x.low = y - (total - x.u)
        x.u = total
        if wp.static(sliding):
            for c in range(constraints.n_sliding):
                row = constraints.slide[a, c]
                if row >= 0:
                    n = constraints.slide_normals[row]
                    x.u = x.u - wp.dot(x.u, n) * n
                    x.du = x.du - wp.dot(x.du, n) * n
                    x.low = x.low - wp.dot(x.low, n) * n
        if k >= 0:
            m = constraints.mask[k]
            shape = constraints.shapes[k]
            v = constraints.value[k * n_models + b]
            target = load_factor(t, t_total, shape[0]) * v
            if shape[1] != shape[0] or shape[2] != shape[0]:  # components on their own curves
                target = wp.vec3(target[0], load_factor(t, t_total, shape[1]) * v[1],
                                 load_factor(t, t_total, shape[2]) * v[2])
            previous = x.u - x.du
            x.u = set_component(x.u, m, target)
            x.du = set_component(x.du, m, target - previous)
            x.low = set_component(x.low, m, wp.vec3(0.0))
        for p in range(plates.n_plates):
            slot = plates.slot[a, p]
            if slot >= 0:
                x = touch_plate(x, a, b * plates.n_plates + p, slot * n_models + b, s, f - external, plates,
                                with_friction)
        u[i] = x.u
        du[i] = x.du
        low[i] = x.low

    return advance_nodes
