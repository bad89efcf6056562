"""Warp kernels of the TLED solver (total Lagrangian explicit dynamics).

All kernels work on a batch of B models that share one mesh, models innermost: node arrays hold
N*B entries (model b's node a at a*B + b), element arrays M*B (element e at e*B + b), ANP slot
arrays S*B, so that the threads of one element (or node) for the B models are neighbours: they
read the element's connectivity and shape-function derivatives once between them, and their
displacements and forces side by side. Materials are a table of rows shared by the elements of a
tissue (:class:`MaterialTable`). Nodal forces are three planes of floats, one per
component (``forces[c, a*B + b]``, :func:`add_force` and :func:`force_at`): the element kernel's
atomic adds of one component then fall on consecutive addresses, where a vec3 array spreads them
over three times as many memory sectors (an ANP step 18-21 % faster on the H200 at 160k-2M tets,
docs/benchmarks.md). Units inside the kernels are SI:
metres, pascal, kilograms, seconds, newtons. Vectors are in the mesh frame (LPS axes).

The step kernels work on a *list* of n models, ``models[:n]`` (the models still moving in a
relaxation, every model otherwise; n a launch parameter): thread t handles entry t mod n of the
list for element (or node) t div n, so the listed models' work is packed into consecutive threads
whatever the batch size, and a launch needs only n x (elements or nodes) threads (more are allowed;
they return at once). With every model listed (n = B) the list is not read at all. Until 2026-11-28
every kernel ran B threads per element and converged models' threads returned: fitted over a fit's
batches of 16 on a 54k-tet mesh, a step cost about 65 us however few models still moved, against 30
us for one slow model solved alone (H200, docs/benchmarks.md). For longer lists the element
kernels' ``_shared`` variants run L = ceil(n / K) threads ("lanes") an element, lane l computing
the entries l, l + L, l + 2L, ... (K from :data:`BreastBiomechLib.solver.tled.MODELS_PER_THREAD`):
a thread reads and indexes its element's connectivity, derivatives and volume once for its models,
and neighbouring lanes' models still lie side by side in memory (a batch of 64 steps 10-12 % faster,
of 16 5 %; H200, docs/benchmarks.md). Once half of a batch has stopped, the solver packs it down to
the models still moving (:mod:`BreastBiomechLib.solver.packing`): the kernels see a smaller batch.
The element kernels are built per formulation (:func:`element_kernels`: the ANP mode, Prony terms
or none, ANP slots that are the nodes or not, as compile-time constants), so that each holds only
its formulation's branches and registers.
"""

from __future__ import annotations

import collections
import functools
import inspect

import warp as wp

# CUDA builds of this module use fast math (approximate division, square root and powers, denormals
# flushed; no reassociation, so the compensated displacement sum holds): the element kernel's
# divisions and powers are a good part of its time, and a step costs 12-13 % less at 160k tets and
# in batches of 64, 7 % less at 2M (H200, docs/benchmarks.md). warp's CPU builds ignore the option:
# CPU results are unchanged.
wp.set_module_options({"fast_math": True})

# load curves, numbered as in model.LOAD_SHAPES (NiftySim's shapes)
LOAD_POLY345 = 0
LOAD_RAMP = 1
LOAD_STEP = 2
LOAD_RAMPHOLD = 3
LOAD_HILLY = 4


@wp.func
def load_factor(t: float, total: float, shape: int) -> float:
    """Relative load at time t, r = t/total clamped to [0, 1]: POLY345 10r^3 - 15r^4 + 6r^5, RAMP r,
    STEP 1, RAMPHOLD min(r / 0.1, 1), HILLY r exp(cos(4 pi r) - 1) (NiftySim's curves)."""
    r = wp.clamp(t / total, 0.0, 1.0)
    if shape == LOAD_RAMP:
        return r
    if shape == LOAD_STEP:
        return 1.0
    if shape == LOAD_RAMPHOLD:
        return wp.min(r / 0.1, 1.0)
    if shape == LOAD_HILLY:
        return r * wp.exp(wp.cos(4.0 * wp.pi * r) - 1.0)
    return r * r * r * (10.0 + r * (-15.0 + 6.0 * r))


@wp.func
def deformation_gradient(u: wp.array(dtype=wp.vec3), b: int, n_models: int, n0: int, n1: int, n2: int, n3: int,
                         d0: wp.vec3, d1: wp.vec3, d2: wp.vec3, d3: wp.vec3) -> wp.mat33:
    """F = I + sum_a u_a (x) dN_a/dX of model b."""
    return (wp.identity(n=3, dtype=float) + wp.outer(u[n0 * n_models + b], d0) + wp.outer(u[n1 * n_models + b], d1)
            + wp.outer(u[n2 * n_models + b], d2) + wp.outer(u[n3 * n_models + b], d3))


@wp.func
def isochoric_stress(C: wp.mat33, Cinv: wp.mat33, J: float, mu: float, eta: float, a: wp.vec3) -> wp.mat33:
    """Isochoric second Piola-Kirchhoff stress 2 dW_iso/dC, W_iso = mu/2 (I1bar - 3) + eta/2 (I4bar - 1)^2,
    from C = F^T F, its inverse and J = det F (computed once per element for both stress parts)."""
    J23 = wp.pow(J, -2.0 / 3.0)
    S = mu * J23 * (wp.identity(n=3, dtype=float) - ((C[0, 0] + C[1, 1] + C[2, 2]) / 3.0) * Cinv)
    if eta > 0.0:
        I4 = wp.dot(a, C * a)
        S = S + 2.0 * eta * (J23 * I4 - 1.0) * J23 * (wp.outer(a, a) - (I4 / 3.0) * Cinv)
    return S


@wp.func
def visco_first_piola(F: wp.mat33, J: float, mu: float, kappa: float, eta: float, a: wp.vec3, v0: float,
                      first: int, n_terms: int, prony_g: wp.array(dtype=float), prony_decay: wp.array(dtype=float),
                      visco_state: wp.array(dtype=wp.mat33), update_state: int) -> wp.mat33:
    """V0 P (N m) of a visco-hyperelastic element at F, det F = ``J`` (ANP's F scaled to its
    dilatation, see :func:`scaled_first_piola`): S = S_iso + kappa J (J - 1) C^-1 - sum_i g_i Q_i
    over the element's ``n_terms`` Prony terms stored from ``first`` on, with dQ_i/dt = (S_iso -
    Q_i) / tau_i integrated exactly for S_iso (:func:`isochoric_stress`) constant over the step,
    Q_i <- d_i Q_i + (1 - d_i) S_iso, d_i = exp(-dt / tau_i), where ``update_state`` is set. The
    hyperelastic elements take :func:`scaled_first_piola`, which forms no C^-1: with this path's
    registers in their kernel they ran 5-8 % slower in batches (H200, docs/benchmarks.md)."""
    C = wp.transpose(F) * F
    Cinv = wp.inverse(C)
    S_iso = isochoric_stress(C, Cinv, J, mu, eta, a)
    S = S_iso + kappa * J * (J - 1.0) * Cinv
    for i in range(n_terms):
        slot = first + i
        Q = visco_state[slot]
        if update_state != 0:
            Q = prony_decay[slot] * Q + (1.0 - prony_decay[slot]) * S_iso
            visco_state[slot] = Q
        S = S - prony_g[slot] * Q
    return v0 * (F * S)


@wp.func
def cofactor(F: wp.mat33) -> wp.mat33:
    """cof F = det(F) F^-T: its rows are the cross products of F's rows (1-2, 2-0, 0-1), and det F
    is the dot product of F's first row with the first of these."""
    r0 = wp.vec3(F[0, 0], F[0, 1], F[0, 2])
    r1 = wp.vec3(F[1, 0], F[1, 1], F[1, 2])
    r2 = wp.vec3(F[2, 0], F[2, 1], F[2, 2])
    return wp.matrix_from_rows(wp.cross(r1, r2), wp.cross(r2, r0), wp.cross(r0, r1))


@wp.func
def scaled_first_piola(F: wp.mat33, cof: wp.mat33, J: float, Jm: float, scale: float, mu: float, kappa: float,
                       eta: float, a: wp.vec3, v0: float) -> wp.mat33:
    """V0 P(Fbar) (N m): the first Piola-Kirchhoff stress (Pa) times the element's volume ``v0`` (m^3) at
    Fbar = ``scale`` F, det Fbar = ``Jm`` (ANP's dilatation; ``scale`` = (Jm / J)^(1/3), 1 and
    ``Jm`` = J without ANP), given F, its cofactor ``cof`` and J = det F, for
    W = mu/2 (I1bar - 3) + kappa/2 (J - 1)^2 + eta/2 (I4bar - 1)^2 (fibre ``a``, unit).

    P = Fbar S with S = 2 dW/dC, written with Fbar C^-1 = Fbar^-T = cof F / (scale J) so that
    neither C nor its inverse is formed: P = mu Jm^(-2/3) (Fbar - I1 / 3 Fbar^-T) + kappa Jm (Jm - 1)
    Fbar^-T + 2 eta (Jm^(-2/3) I4 - 1) Jm^(-2/3) (Fbar a (x) a - I4 / 3 Fbar^-T), I1 = |Fbar|^2 and
    I4 = |Fbar a|^2. This is Fbar times :func:`isochoric_stress` plus the volumetric stress kappa Jm
    (Jm - 1) C^-1 in less arithmetic (the element kernel alone 8.8 against 9.3-10.0 us at 160k tets,
    a lone model's step 4-5 % faster; batches, not bound by this arithmetic, within 1 %; H200,
    docs/benchmarks.md), and the volumetric part takes ANP's Jm as it is rather than det Fbar
    recomputed (which differs from it by float32 round-off, times kappa)."""
    j23 = wp.pow(Jm, -2.0 / 3.0)
    inverse = 1.0 / (scale * J)  # Fbar^-T = inverse cof F
    shear = mu * j23
    # times F and times cof F; at F = I exactly shear and -shear (I1 / 3 = 1), so no stress at rest
    P = (shear * scale) * F
    across = (kappa * Jm * (Jm - 1.0) - shear * (scale * scale * wp.ddot(F, F) / 3.0)) * inverse
    if eta > 0.0:
        fa = scale * (F * a)
        i4 = wp.dot(fa, fa)
        c = 2.0 * eta * (j23 * i4 - 1.0) * j23
        P = P + c * wp.outer(fa, a)
        across = across - c * (i4 / 3.0) * inverse
    return v0 * (P + across * cof)


@wp.func
def strain_energy_density(F: wp.mat33, mu: float, kappa: float, eta: float, a: wp.vec3) -> float:
    C = wp.transpose(F) * F
    J = wp.determinant(F)
    J23 = wp.pow(J, -2.0 / 3.0)
    W = 0.5 * mu * (J23 * (C[0, 0] + C[1, 1] + C[2, 2]) - 3.0) + 0.5 * kappa * (J - 1.0) * (J - 1.0)
    if eta > 0.0:
        I4b = J23 * wp.dot(a, C * a)
        W = W + 0.5 * eta * (I4b - 1.0) * (I4b - 1.0)
    return W


@wp.func
def listed(models: wp.array(dtype=int), n_listed: int, n_models: int, tid: int) -> wp.vec2i:
    """(item, model) of thread ``tid`` over the ``n_listed`` models ``models[:n_listed]``: item
    ``tid`` div n_listed (an element or node) of model ``models[tid mod n_listed]``, or of model
    ``tid mod n_models`` without a read where every model is listed (a read less in front of
    each thread's first loads: the step is bound by their latency), and without the integer
    division for a list of one (a lone model's step is bound by its threads' instruction count,
    which the division adds to); item -1 for an empty list."""
    if n_listed <= 0:
        return wp.vec2i(-1, 0)
    if n_listed == 1:  # a lone model (or a batch's last one moving): no division
        if n_models == 1:
            return wp.vec2i(tid, 0)
        return wp.vec2i(tid, models[0])
    item = tid // n_listed
    entry = tid - item * n_listed
    if n_listed == n_models:
        return wp.vec2i(item, entry)
    return wp.vec2i(item, models[entry])


@wp.func
def element_and_lane(lanes: int, tid: int) -> wp.vec2i:
    """(element, lane) of thread ``tid`` of a ``_shared`` element kernel, which runs ``lanes``
    threads an element (see the module's docstring)."""
    if lanes == 1:
        return wp.vec2i(tid, 0)
    e = tid // lanes
    return wp.vec2i(e, tid - e * lanes)


@wp.func
def model_at(models: wp.array(dtype=int), n_listed: int, n_models: int, entry: int) -> int:
    """The model of entry ``entry`` of the list ``models[:n_listed]`` (the entry itself where every
    model is listed: no read)."""
    if n_listed == n_models:
        return entry
    return models[entry]


@wp.func
def add_force(forces: wp.array2d(dtype=float), i: int, f: wp.vec3):
    """forces[:, i] += f (N), one atomic add per component plane."""
    wp.atomic_add(forces, 0, i, f[0])
    wp.atomic_add(forces, 1, i, f[1])
    wp.atomic_add(forces, 2, i, f[2])


@wp.func
def force_at(forces: wp.array2d(dtype=float), i: int) -> wp.vec3:
    """The force (N) of entry i of the component planes."""
    return wp.vec3(forces[0, i], forces[1, i], forces[2, i])


@wp.struct
class ElementMaterial:
    """One model's material in a :class:`MaterialTable` row: mu, kappa, eta (Pa), the fibre's unit
    vector (LPS axes); one record, so that a thread finds it with one address computation, not four."""
    mu: float
    kappa: float
    eta: float
    fibre: wp.vec3


@wp.struct
class MaterialTable:
    """The elements' materials as the kernels read them: a table of rows shared by the elements
    whose materials agree in every model of the batch (a tissue, mostly), ``row[e]`` element e's;
    row r's :class:`ElementMaterial` for model b at ``values[r * B + b]``. The threads of a tissue's
    elements then read a few cached entries, not one each (about 9 % of the element kernel's time
    at 2M tets, docs/benchmarks.md)."""
    row: wp.array(dtype=int)
    values: wp.array(dtype=ElementMaterial)


@wp.func
def material_of(materials: MaterialTable, e: int, n_models: int, b: int) -> ElementMaterial:
    """Element e's material in model b."""
    return materials.values[materials.row[e] * n_models + b]


# ANP (average nodal pressure) modes of the element kernels
ANP_OFF = wp.constant(0)
ANP_WITHIN_MATERIALS = wp.constant(1)  # a slot per node and bulk modulus (tled.anp_slots)
ANP_ACROSS_MATERIALS = wp.constant(2)  # a slot per node, whatever its elements' materials (NiftySim's)


@wp.func
def element_slots(tets: wp.array2d(dtype=int), slots: wp.array2d(dtype=int), slots_are_nodes: int,
                  e: int) -> wp.vec4i:
    """Element e's four ANP slots: its nodes where ``slots_are_nodes`` (one slot per node: a
    read of the connectivity, which the kernels read anyway), else ``slots[e]``."""
    if slots_are_nodes != 0:
        return wp.vec4i(tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3])
    return wp.vec4i(slots[e, 0], slots[e, 1], slots[e, 2], slots[e, 3])


@wp.func
def model_volume_change(u: wp.array(dtype=wp.vec3), e: int, b: int, n_models: int, n0: int, n1: int, n2: int,
                        n3: int, s: wp.vec4i, d0: wp.vec3, d1: wp.vec3, d2: wp.vec3, d3: wp.vec3, v0: float,
                        materials: MaterialTable, anp: int, anp_sums: wp.array(dtype=float)):
    """:func:`nodal_pressure`'s work for element e of model b, given the element's nodes, slots,
    shape derivatives and volume (for :func:`nodal_pressure_shared`; :func:`nodal_pressure` keeps
    its own copy of these lines, see :func:`model_element_forces`)."""
    F = deformation_gradient(u, b, n_models, n0, n1, n2, n3, d0, d1, d2, d3)
    change = (wp.determinant(F) - 1.0) * v0
    if anp == ANP_ACROSS_MATERIALS:
        change = material_of(materials, e, n_models, b).kappa * change
    wp.atomic_add(anp_sums, s[0] * n_models + b, change)
    wp.atomic_add(anp_sums, s[1] * n_models + b, change)
    wp.atomic_add(anp_sums, s[2] * n_models + b, change)
    wp.atomic_add(anp_sums, s[3] * n_models + b, change)


@wp.func
def record_inversion(inverted: wp.array(dtype=int), b: int, e: int, step: int):
    """Count an inverted element of model b, keeping the first one found and its step."""
    if wp.atomic_add(inverted, 4 * b, 1) == 0:
        inverted[4 * b + 1] = e
        inverted[4 * b + 2] = step


@wp.func
def mean_slot_change(anp_sums: wp.array(dtype=float), slot_volume: wp.array(dtype=float), s: wp.vec4i, b: int,
                     n_models: int) -> float:
    """The mean over an element's four ANP slots ``s`` of model b's sums per slot volume (Jm - 1
    within materials; the mean pressure across them, see :func:`element_kernels`)."""
    return 0.25 * (anp_sums[s[0] * n_models + b] / slot_volume[s[0]]
                   + anp_sums[s[1] * n_models + b] / slot_volume[s[1]]
                   + anp_sums[s[2] * n_models + b] / slot_volume[s[2]]
                   + anp_sums[s[3] * n_models + b] / slot_volume[s[3]])


@wp.func
def model_element_forces(u: wp.array(dtype=wp.vec3), e: int, b: int, n_models: int, n0: int, n1: int, n2: int,
                         n3: int, d0: wp.vec3, d1: wp.vec3, d2: wp.vec3, d3: wp.vec3, v0: float,
                         materials: MaterialTable, anp: int, tets: wp.array2d(dtype=int),
                         slots: wp.array2d(dtype=int), slots_are_nodes: int, slot_volume: wp.array(dtype=float),
                         anp_sums: wp.array(dtype=float), n_terms: int, prony_g: wp.array(dtype=float),
                         prony_decay: wp.array(dtype=float), visco_state: wp.array(dtype=wp.mat33),
                         update_state: int, clock: wp.array(dtype=int), forces: wp.array2d(dtype=float),
                         inverted: wp.array(dtype=int)):
    """:func:`element_forces`' work for element e of model b, given the element's nodes, shape
    derivatives ``d0``-``d3`` and volume ``v0``, for :func:`element_forces_shared` (its ANP slots and
    their volumes are read here, for each model from the cache: held in registers across a
    thread's models they cost the kernel occupancy). :func:`element_forces`, a thread per element
    and model, makes its own reads (the element's with the model's, in one round): built on this
    function its lone 2M-tet step took 170-173 us against 163-165 (H200, 2026-12-01,
    docs/benchmarks.md). Its stress lines are copied there (see the comment in it)."""
    # every read that does not depend on another first, so that they are in flight together (a
    # frozen model's flag too: tested once the element's reads are on their way)
    frozen = inverted[4 * b + 3]
    m = material_of(materials, e, n_models, b)
    mean = float(0.0)  # of the slots' sums per volume
    if anp != ANP_OFF:
        mean = mean_slot_change(anp_sums, slot_volume, element_slots(tets, slots, slots_are_nodes, e), b, n_models)
    F = deformation_gradient(u, b, n_models, n0, n1, n2, n3, d0, d1, d2, d3)
    if frozen != 0:
        return
    cof = cofactor(F)
    J = F[0, 0] * cof[0, 0] + F[0, 1] * cof[0, 1] + F[0, 2] * cof[0, 2]
    if J <= 0.0:
        record_inversion(inverted, b, e, clock[0])
        return
    Jm = J
    scale = float(1.0)
    if anp != ANP_OFF:
        # across materials the sums are pressures; within, volume changes (divided by 1, exactly)
        Jm = mean / wp.where(anp == ANP_ACROSS_MATERIALS, m.kappa, 1.0) + 1.0
        if Jm <= 0.0:
            record_inversion(inverted, b, e, clock[0])
            return
        scale = wp.pow(Jm / J, 1.0 / 3.0)
    if n_terms > 0:
        j = e * n_models + b  # the element's entry of model b (visco state)
        P = visco_first_piola(scale * F, Jm, m.mu, m.kappa, m.eta, m.fibre, v0, j * n_terms, n_terms, prony_g,
                              prony_decay, visco_state, update_state)
    else:
        P = scaled_first_piola(F, cof, J, Jm, scale, m.mu, m.kappa, m.eta, m.fibre, v0)
    add_force(forces, n0 * n_models + b, P * d0)
    add_force(forces, n1 * n_models + b, P * d1)
    add_force(forces, n2 * n_models + b, P * d2)
    add_force(forces, n3 * n_models + b, P * d3)


ElementKernels = collections.namedtuple("ElementKernels", "nodal_pressure nodal_pressure_shared element_forces "
                                                         "element_forces_shared")

# the specialised element kernels' options: a module of their own each (fast math as this module's)
SPECIALISED = {"module": "unique", "module_options": {"fast_math": True}}


@functools.cache
def element_kernels(anp_mode: int, visco: bool, node_slots: bool) -> ElementKernels:
    """The element kernels for one formulation: ANP mode ``anp_mode`` (``ANP_*``), Prony terms
    (``visco``) or none, and ANP slots that are the elements' nodes (``node_slots``, see
    :func:`element_slots`) or a table of their own. These are compile-time constants of the
    kernels, so a kernel holds only its formulation's arithmetic, branches and registers (the
    batch element kernel 803 static instructions and 80 registers against 1 229 and 96 built for
    every formulation; batches of 64 and 16 models 10 % faster, a lone 2M-tet model 3 %; H200,
    docs/benchmarks.md). Each combination is compiled once, on its first launch, in a warp module
    of its own; the kernels take the arguments the general build did, less ``anp`` and
    ``slots_are_nodes``."""

    @wp.kernel(name="nodal_pressure", **SPECIALISED)
    def nodal_pressure(u: wp.array(dtype=wp.vec3), tets: wp.array2d(dtype=int), slots: wp.array2d(dtype=int),
                       dhdx: wp.array2d(dtype=wp.vec3), vol0: wp.array(dtype=float),
                       materials: MaterialTable, n_models: int, models: wp.array(dtype=int), n_listed: int,
                       anp_sums: wp.array(dtype=float)):
        """ANP pass 1: accumulate each element's volume change (J_e - 1) V_e (m^3) at its ANP slots
        (:func:`element_slots`), for the listed ``models`` (see the module's docstring; converged
        models stand still). With ``anp`` = :data:`ANP_WITHIN_MATERIALS` each slot gathers the
        elements of one node and one bulk modulus (:func:`BreastBiomechLib.solver.tled.anp_slots`):
        the nodal pressure is that modulus times the slot's volume change per volume, and the modulus
        cancels from the mean dilatation :func:`element_forces` takes from it, so the sums leave it
        out and this kernel reads no material (a dependent read less: this pass is bound by the
        latency of its reads). With :data:`ANP_ACROSS_MATERIALS` (one slot per node) the sums are of
        the pressures kappa_e (J_e - 1) V_e (Pa m^3)."""
        anp = wp.static(anp_mode)  # constants of this specialisation (see element_kernels)
        slots_are_nodes = wp.static(int(node_slots))
        at = listed(models, n_listed, n_models, wp.tid())
        e, b = at[0], at[1]
        if e < 0 or e >= tets.shape[0]:
            return
        n0, n1, n2, n3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
        s = element_slots(tets, slots, slots_are_nodes, e)
        v0 = vol0[e]
        F = deformation_gradient(u, b, n_models, n0, n1, n2, n3, dhdx[e, 0], dhdx[e, 1], dhdx[e, 2], dhdx[e, 3])
        change = (wp.determinant(F) - 1.0) * v0
        if anp == ANP_ACROSS_MATERIALS:
            change = material_of(materials, e, n_models, b).kappa * change
        wp.atomic_add(anp_sums, s[0] * n_models + b, change)
        wp.atomic_add(anp_sums, s[1] * n_models + b, change)
        wp.atomic_add(anp_sums, s[2] * n_models + b, change)
        wp.atomic_add(anp_sums, s[3] * n_models + b, change)

    @wp.kernel(name="nodal_pressure_shared", **SPECIALISED)
    def nodal_pressure_shared(u: wp.array(dtype=wp.vec3), tets: wp.array2d(dtype=int),
                              slots: wp.array2d(dtype=int), dhdx: wp.array2d(dtype=wp.vec3),
                              vol0: wp.array(dtype=float), materials: MaterialTable, n_models: int,
                              models: wp.array(dtype=int), n_listed: int, anp_sums: wp.array(dtype=float),
                              lanes: int):
        """:func:`nodal_pressure` with ``lanes`` threads an element, each for several of the listed
        models (see the module's docstring), reading its element's data once for them."""
        anp = wp.static(anp_mode)  # constants of this specialisation (see element_kernels)
        slots_are_nodes = wp.static(int(node_slots))
        at = element_and_lane(lanes, wp.tid())
        e = at[0]
        if e >= tets.shape[0]:
            return
        n0, n1, n2, n3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
        s = element_slots(tets, slots, slots_are_nodes, e)
        d0, d1, d2, d3, v0 = dhdx[e, 0], dhdx[e, 1], dhdx[e, 2], dhdx[e, 3], vol0[e]
        entry = at[1]
        while entry < n_listed:
            model_volume_change(u, e, model_at(models, n_listed, n_models, entry), n_models, n0, n1, n2, n3, s,
                                d0, d1, d2, d3, v0, materials, anp, anp_sums)
            entry += lanes

    @wp.kernel(name="element_forces", **SPECIALISED)
    def element_forces(u: wp.array(dtype=wp.vec3), tets: wp.array2d(dtype=int), dhdx: wp.array2d(dtype=wp.vec3),
                       vol0: wp.array(dtype=float), materials: MaterialTable, slots: wp.array2d(dtype=int),
                       anp_sums: wp.array(dtype=float), slot_volume: wp.array(dtype=float),
                       n_terms: int, prony_g: wp.array(dtype=float), prony_decay: wp.array(dtype=float),
                       visco_state: wp.array(dtype=wp.mat33), update_state: int,
                       n_models: int, clock: wp.array(dtype=int), models: wp.array(dtype=int), n_listed: int,
                       forces: wp.array2d(dtype=float), inverted: wp.array(dtype=int)):
        """Internal nodal forces f_a = V0 F S dN_a/dX; with ANP (``anp`` not :data:`ANP_OFF`) F is
        scaled to the dilatation Jm of the mean of the averaged pressures at the element's slots, as
        NiftySim's T4ANP, from :func:`nodal_pressure`'s sums (Jm - 1 the mean of the slots' volume
        changes per volume within materials; across them, the mean pressure over kappa_e).
        Visco terms (``n_terms`` per element): S = S_vol + S_iso - sum_i g_i Q_i
        with dQ_i/dt = (S_iso - Q_i) / tau_i, integrated exactly for a stress constant over the step
        (Q_i <- d_i Q_i + (1 - d_i) S_iso, d_i = exp(-dt / tau_i)) when ``update_state`` is set.
        Elements with J <= 0 are counted per model, the first one and its step recorded in
        ``inverted[4b:4b+4]`` = [count, element, step, frozen] of model b; once frozen that model
        stands still (the others of the batch go on), keeping its last configuration for
        inspection instead of producing NaN (frozen is 1 then; 2 for a model a relaxation has found
        converged, :mod:`BreastBiomechLib.solver.relaxation`). Only the listed ``models`` are computed
        (see the module's docstring): converged models stand still, so their forces no longer change
        anything.

        The step is ``clock[0]``, copied to ``clock[1]`` for :func:`advance_nodes`, which advances
        it."""
        anp = wp.static(anp_mode)  # constants of this specialisation (see element_kernels)
        slots_are_nodes = wp.static(int(node_slots))
        terms = n_terms
        if wp.static(not visco):
            terms = 0
        tid = wp.tid()
        if tid == 0:
            clock[1] = clock[0]
        at = listed(models, n_listed, n_models, tid)
        e, b = at[0], at[1]
        if e < 0 or e >= tets.shape[0]:
            return
        # every read that does not depend on another first, so that they are in flight together (a
        # frozen model's flag too: tested once the element's reads are on their way)
        frozen = inverted[4 * b + 3]
        n0, n1, n2, n3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
        d0, d1, d2, d3 = dhdx[e, 0], dhdx[e, 1], dhdx[e, 2], dhdx[e, 3]
        m = material_of(materials, e, n_models, b)
        v0 = vol0[e]
        mean = float(0.0)  # of the slots' sums per volume
        if anp != ANP_OFF:
            mean = mean_slot_change(anp_sums, slot_volume, element_slots(tets, slots, slots_are_nodes, e), b, n_models)
        F = deformation_gradient(u, b, n_models, n0, n1, n2, n3, d0, d1, d2, d3)
        if frozen != 0:
            return
        # model_element_forces' stress lines, copied: as a call the element's nodes and derivatives
        # stay in registers through it, where here they are read again from the cache after the
        # stress (64 registers against 72 with a slot table, 72 against 80 with Prony terms; sm_90)
        cof = cofactor(F)
        J = F[0, 0] * cof[0, 0] + F[0, 1] * cof[0, 1] + F[0, 2] * cof[0, 2]
        if J <= 0.0:
            record_inversion(inverted, b, e, clock[0])
            return
        Jm = J
        scale = float(1.0)
        if anp != ANP_OFF:
            # across materials the sums are pressures; within, volume changes (divided by 1, exactly)
            Jm = mean / wp.where(anp == ANP_ACROSS_MATERIALS, m.kappa, 1.0) + 1.0
            if Jm <= 0.0:
                record_inversion(inverted, b, e, clock[0])
                return
            scale = wp.pow(Jm / J, 1.0 / 3.0)
        if terms > 0:
            j = e * n_models + b  # the element's entry of model b (visco state)
            P = visco_first_piola(scale * F, Jm, m.mu, m.kappa, m.eta, m.fibre, v0, j * terms, terms, prony_g,
                                  prony_decay, visco_state, update_state)
        else:
            P = scaled_first_piola(F, cof, J, Jm, scale, m.mu, m.kappa, m.eta, m.fibre, v0)
        add_force(forces, n0 * n_models + b, P * d0)
        add_force(forces, n1 * n_models + b, P * d1)
        add_force(forces, n2 * n_models + b, P * d2)
        add_force(forces, n3 * n_models + b, P * d3)

    @wp.kernel(name="element_forces_shared", **SPECIALISED)
    def element_forces_shared(u: wp.array(dtype=wp.vec3), tets: wp.array2d(dtype=int),
                              dhdx: wp.array2d(dtype=wp.vec3), vol0: wp.array(dtype=float),
                              materials: MaterialTable, slots: wp.array2d(dtype=int),
                              anp_sums: wp.array(dtype=float), slot_volume: wp.array(dtype=float),
                              n_terms: int, prony_g: wp.array(dtype=float), prony_decay: wp.array(dtype=float),
                              visco_state: wp.array(dtype=wp.mat33), update_state: int, n_models: int,
                              clock: wp.array(dtype=int), models: wp.array(dtype=int), n_listed: int,
                              forces: wp.array2d(dtype=float), inverted: wp.array(dtype=int), lanes: int):
        """:func:`element_forces` with ``lanes`` threads an element, each for several of the listed
        models (see the module's docstring), reading its element's nodes, derivatives and volume once
        for them. A kernel of its own: with the loop in :func:`element_forces` a lone model's 2M-tet
        step took 173-180 us against 163-165 (H200, 2026-12-01, docs/benchmarks.md)."""
        anp = wp.static(anp_mode)  # constants of this specialisation (see element_kernels)
        slots_are_nodes = wp.static(int(node_slots))
        terms = n_terms
        if wp.static(not visco):
            terms = 0
        tid = wp.tid()
        if tid == 0:
            clock[1] = clock[0]
        at = element_and_lane(lanes, tid)
        e = at[0]
        if e >= tets.shape[0]:
            return
        n0, n1, n2, n3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
        d0, d1, d2, d3, v0 = dhdx[e, 0], dhdx[e, 1], dhdx[e, 2], dhdx[e, 3], vol0[e]
        entry = at[1]
        while entry < n_listed:
            model_element_forces(u, e, model_at(models, n_listed, n_models, entry), n_models, n0, n1, n2, n3,
                                 d0, d1, d2, d3, v0, materials, anp, tets, slots, slots_are_nodes, slot_volume,
                                 anp_sums, terms, prony_g, prony_decay, visco_state, update_state, clock, forces,
                                 inverted)
            entry += lanes

    return ElementKernels(nodal_pressure, nodal_pressure_shared, element_forces, element_forces_shared)


@wp.func
def set_component(x: wp.vec3, mask: wp.vec3, value: wp.vec3) -> wp.vec3:
    """x with the components where mask > 0 replaced by value's."""
    return wp.vec3(wp.where(mask[0] > 0.0, value[0], x[0]), wp.where(mask[1] > 0.0, value[1], x[1]),
                   wp.where(mask[2] > 0.0, value[2], x[2]))


@wp.func
def clipped(v: wp.vec3, limit: float) -> wp.vec3:
    """v shortened to length ``limit`` where it is longer."""
    length = wp.length(v)
    if length > limit and length > 0.0:
        return v * (limit / length)
    return v


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


@wp.struct
class NodeConstraints:
    """Sliding supports and prescribed components, looked up per node.

    ``slide[a, s]``: node a's row in ``slide_normals`` for sliding support s, or -1 (one column
    per sliding support, at least one; ``n_sliding`` of them in use). ``constrained[a]``: node a's row K in the merged
    constraints, or -1; its ``mask[K]`` (1 where prescribed), ``shapes[K]`` (load curve per
    component) and final values ``value[K * B + b]`` (m) for model b."""
    slide: wp.array2d(dtype=int)
    n_sliding: int
    slide_normals: wp.array(dtype=wp.vec3)
    constrained: wp.array(dtype=int)
    mask: wp.array(dtype=wp.vec3)
    shapes: wp.array(dtype=wp.vec3i)
    value: wp.array(dtype=wp.vec3)
    n_constrained: int


@wp.struct
class PlatePose:
    """One plate of one model: ``point`` (m) and ``normal`` (unit, towards the tissue) at the
    start, ``motion`` (m) over the load, the flat face's end ``edge_distance`` (m) from the point
    along ``edge_direction`` (unit, in the face's plane) with a fillet of radius ``edge_radius``
    (m), and the Coulomb ``friction`` coefficient (0: frictionless). One record, so that a node
    thread finds a plate's pose with one address computation."""
    point: wp.vec3
    normal: wp.vec3
    motion: wp.vec3
    edge_direction: wp.vec3
    edge_distance: float
    edge_radius: float
    friction: float


@wp.struct
class PlateContact:
    """Rigid plates (P per model; model b's plate p at q = b P + p) and their contact nodes.

    ``slot[a, p]``: node a's contact slot for plate p, or -1 (slots of all plates numbered one
    after another); per slot and model, at ``slot * B + b`` (models innermost, as the nodes), the
    friction state, ``anchor`` (where the node sticks on the plate, m) and ``touching``, and
    ``force``, the force (N) the plate applied to the tissue through that node in the model's
    last step (zero where it did not touch; :func:`plate_forces` sums them).
    ``pose[q]`` plate q's :class:`PlatePose`; ``x0`` the reference node positions (m)."""
    slot: wp.array2d(dtype=int)
    n_plates: int
    x0: wp.array(dtype=wp.vec3)
    pose: wp.array(dtype=PlatePose)
    anchor: wp.array(dtype=wp.vec3)
    touching: wp.array(dtype=int)
    force: wp.array(dtype=wp.vec3)


@wp.struct
class NodeState:
    """One node's displacement ``u`` (m), its float32 rounding remainder ``low`` (see
    :func:`advance_nodes`) and its last increment ``du`` (m), held in registers while a step
    updates them."""
    u: wp.vec3
    du: wp.vec3
    low: wp.vec3


@wp.func
def touch_plate(x: NodeState, node: int, q: int, state: int, s: float, contact: wp.vec3,
                plates: PlateContact, with_friction: int) -> NodeState:
    """Node ``node`` (its state ``x``, returned updated) in kinematic contact with rigid plate q at load
    factor s: a node behind the plate is moved back onto its surface along the surface normal by
    the depth d it went in. A plate's flat face ends ``edge_distance`` along ``edge_direction``
    from its point (:class:`PlatePose`), in a convex rounded edge of radius ``edge_radius``;
    beyond it the plate has ended (an unbounded plate has a huge distance). The fillet lies behind
    the face's plane, so a node in front of that plane touches nothing, and is done with first
    (the warps of nodes that all face a plate from afar skip the rest).

    Coulomb friction (mu > 0), by return mapping: the node's position on the plate (relative to
    the moving plate, ``anchor[state]``) is kept from its first contact (``touching[state]``);
    each step it is pulled back tangentially to that point (stick) unless the pull t exceeds mu d,
    when it moves by mu d towards it and the anchor follows (slip). A kinematic correction c in
    one step stands for the force m c (1 + a dt / 2) / dt^2, the same factor for the normal and
    the tangential part, so |t| <= mu d is |f_t| <= mu f_n whatever the (scaled) mass and
    damping. mu = 0 is frictionless contact; ``with_friction`` 0 (a constant of
    :func:`node_kernel`'s build) makes every plate frictionless.

    ``contact`` is the node's internal minus external (gravity) force (N): the force the plate
    applies to the tissue through the node (``force[state]``, zero without contact) is its normal
    part and, with friction, its tangential part up to mu times the normal part. Stored per
    slot, not summed per plate here: the atomic adds of every touching node onto one plate's
    three numbers queued behind each other, 1-4 us of a 160k-tet step (H200, docs/benchmarks.md)."""
    pose = plates.pose[q]
    rel = plates.x0[node] + x.u - (pose.point + s * pose.motion)
    n = pose.normal
    gap = wp.dot(rel, n)
    mu = wp.where(with_friction != 0, pose.friction, 0.0)
    if gap >= 0.0:  # in front of the face's plane: no contact
        plates.force[state] = wp.vec3(0.0)
        if mu > 0.0:
            plates.touching[state] = 0
        return x
    e = pose.edge_direction
    past = wp.dot(rel, e) - pose.edge_distance
    radius = pose.edge_radius
    normal = n
    depth = float(0.0)  # how far the node lies inside the plate, along ``normal``
    if past <= 0.0:
        depth = -gap
    elif gap > -radius:
        v = past * e + (gap + radius) * n  # from the fillet's centre
        distance = wp.length(v)
        if distance > 0.0:
            normal = v / distance
            depth = radius - distance
    if depth > 0.0:
        correction = depth * normal
        normal_force = wp.dot(contact, normal)
        if mu > 0.0:
            on_plate = rel + correction
            if plates.touching[state] == 0:  # first contact: stick where it touched
                plates.touching[state] = 1
                plates.anchor[state] = on_plate
            else:
                pull = plates.anchor[state] - on_plate
                pull = clipped(pull - wp.dot(pull, normal) * normal, mu * depth)
                plates.anchor[state] = on_plate + pull  # unchanged in stick, the new position in slip
                correction = correction + pull
            x.low = wp.vec3(0.0)
            tangential = clipped(contact - normal_force * normal, mu * wp.max(normal_force, 0.0))
            plates.force[state] = normal_force * normal + tangential
        else:
            x.low = x.low - wp.dot(x.low, normal) * normal
            plates.force[state] = normal_force * normal
        x.u = x.u + correction
        x.du = x.du + correction
    else:
        plates.force[state] = wp.vec3(0.0)
        if mu > 0.0:
            plates.touching[state] = 0
    return x


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


REDUCTION_BLOCK = wp.constant(256)  # threads per block of the per-model sums below


def reduction_launch(kernel, n_models: int, n_items: int, inputs: list) -> None:
    """Launch a per-model reduction kernel over ``n_items`` entries of each of ``n_models``
    models: each model's range padded to whole blocks of :data:`REDUCTION_BLOCK` threads (the
    kernel gets the padded length after ``inputs``), so that a block never mixes two models and
    sums its threads' values before one atomic per block: a single atomic per entry on one
    address per model serialises (160k elements: 0.29 ms per internal-energy sum on an H100)."""
    padded = -(-n_items // REDUCTION_BLOCK) * REDUCTION_BLOCK
    wp.launch(kernel, n_models * padded, inputs + [padded], block_dim=REDUCTION_BLOCK)


@wp.func
def model_and_entry(tid: int, padded: int) -> wp.vec2i:
    """(model, entry) of thread ``tid`` of a :func:`reduction_launch`."""
    b = tid // padded
    return wp.vec2i(b, tid - b * padded)


@wp.kernel
def energies(du: wp.array(dtype=wp.vec3), mass: wp.array(dtype=float), dt: float, n_nodes: int,
             kinetic: wp.array(dtype=float), padded: int):
    """Kinetic energy per model at the last half step, velocity du / dt (J); see :func:`reduction_launch`."""
    at = model_and_entry(wp.tid(), padded)
    value = float(0.0)
    if at[1] < n_nodes:
        i = at[1] * kinetic.shape[0] + at[0]
        v = du[i] / dt
        value = 0.5 * mass[i] * wp.dot(v, v)
    wp.tile_atomic_add(kinetic, wp.tile_sum(wp.tile(value)), offset=at[0])


@wp.kernel
def plate_forces(force: wp.array(dtype=wp.vec3), n_models: int, first: int, count: int, plate: int, n_plates: int,
                 inverted: wp.array(dtype=int), total: wp.array(dtype=float), padded: int):
    """Per model b the force (N, LPS axes) that plate ``plate`` applied to the tissue in the
    model's last step, the sum of its ``count`` contact slots from ``first`` on (see
    :class:`PlateContact`; B = ``n_models``), into ``total[3 (b P + plate) + c]`` for component
    c; nothing for a frozen model (``inverted[4b + 3]``: an inverted element, or converged), as
    no plate touches it. See :func:`reduction_launch`."""
    at = model_and_entry(wp.tid(), padded)
    b, e = at[0], at[1]
    f = wp.vec3(0.0)
    if e < count and inverted[4 * b + 3] == 0:
        f = force[(first + e) * n_models + b]
    q = 3 * (b * n_plates + plate)
    wp.tile_atomic_add(total, wp.tile_sum(wp.tile(f[0])), offset=q)
    wp.tile_atomic_add(total, wp.tile_sum(wp.tile(f[1])), offset=q + 1)
    wp.tile_atomic_add(total, wp.tile_sum(wp.tile(f[2])), offset=q + 2)


@wp.kernel
def internal_energy(u: wp.array(dtype=wp.vec3), tets: wp.array2d(dtype=int), dhdx: wp.array2d(dtype=wp.vec3),
                    vol0: wp.array(dtype=float), materials: MaterialTable, n_nodes: int, n_elements: int,
                    energy: wp.array(dtype=float), padded: int):
    """Stored strain energy per model, sum of V0 W(F) over the elements with J > 0 (J); see
    :func:`reduction_launch`."""
    at = model_and_entry(wp.tid(), padded)
    b, e = at[0], at[1]
    value = float(0.0)
    if e < n_elements:
        F = deformation_gradient(u, b, energy.shape[0], tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3],
                                 dhdx[e, 0], dhdx[e, 1], dhdx[e, 2], dhdx[e, 3])
        if wp.determinant(F) > 0.0:
            m = material_of(materials, e, energy.shape[0], b)
            value = vol0[e] * strain_energy_density(F, m.mu, m.kappa, m.eta, m.fibre)
    wp.tile_atomic_add(energy, wp.tile_sum(wp.tile(value)), offset=b)


@wp.kernel
def relaxation_terms(u_curr: wp.array(dtype=wp.vec3), u_prev: wp.array(dtype=wp.vec3),
                     f_curr: wp.array2d(dtype=float), f_prev: wp.array2d(dtype=float), mass: wp.array(dtype=float),
                     n_nodes: int, stiffness: wp.array(dtype=float), inertia: wp.array(dtype=float), padded: int):
    """Per model: du.K du ~ du.(F(u_curr) - F(u_prev)) and du.M du, du = u_curr - u_prev, for
    dynamic relaxation (Rayleigh quotient of the change since the last update: the lowest
    eigenvalue once transients have died); see :func:`reduction_launch`."""
    at = model_and_entry(wp.tid(), padded)
    k_part = float(0.0)
    m_part = float(0.0)
    if at[1] < n_nodes:
        i = at[1] * stiffness.shape[0] + at[0]
        du = u_curr[i] - u_prev[i]
        k_part = wp.dot(du, force_at(f_curr, i) - force_at(f_prev, i))
        m_part = mass[i] * wp.dot(du, du)
    wp.tile_atomic_add(stiffness, wp.tile_sum(wp.tile(k_part)), offset=at[0])
    wp.tile_atomic_add(inertia, wp.tile_sum(wp.tile(m_part)), offset=at[0])


@wp.kernel
def largest_change(u: wp.array(dtype=wp.vec3), reference: wp.array(dtype=wp.vec3), n_nodes: int,
                   largest: wp.array(dtype=float), padded: int):
    """Per model the largest component of |u - reference| (m); see :func:`reduction_launch`."""
    at = model_and_entry(wp.tid(), padded)
    value = float(0.0)
    if at[1] < n_nodes:
        i = at[1] * largest.shape[0] + at[0]
        value = wp.max(wp.abs(u[i] - reference[i]))
    block = wp.tile_max(wp.tile(value))
    if value == block[0]:  # the block's largest (each thread its own on the CPU, whose tiles hold one lane)
        wp.atomic_max(largest, at[0], value)


@wp.kernel
def perturbed(u: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), eps: float, out: wp.array(dtype=wp.vec3)):
    """out = u + eps v (m): the probe of the finite-difference tangent stiffness."""
    i = wp.tid()
    out[i] = u[i] + eps * v[i]


@wp.kernel
def power_iteration_terms(v: wp.array(dtype=wp.vec3), f_probe: wp.array2d(dtype=float),
                          f_base: wp.array2d(dtype=float), mass: wp.array(dtype=float), eps: float,
                          n_nodes: int, vkv: wp.array(dtype=float), vmv: wp.array(dtype=float),
                          next_v: wp.array(dtype=wp.vec3), largest: wp.array(dtype=float), padded: int):
    """One power iteration on M^-1 K, K v ~ (f(u + eps v) - f(u)) / eps: per model the Rayleigh
    quotient parts v.Kv and v.Mv (its ratio is a lower bound of the largest eigenvalue omega_max^2,
    1/s^2), the next vector M^-1 K v and its largest component (for normalisation); see
    :func:`reduction_launch`."""
    at = model_and_entry(wp.tid(), padded)
    k_part = float(0.0)
    m_part = float(0.0)
    top = float(0.0)
    if at[1] < n_nodes:
        i = at[1] * vkv.shape[0] + at[0]
        kv = (force_at(f_probe, i) - force_at(f_base, i)) / eps
        k_part = wp.dot(v[i], kv)
        m_part = mass[i] * wp.dot(v[i], v[i])
        w = kv / mass[i]
        next_v[i] = w
        top = wp.max(wp.abs(w))
    wp.tile_atomic_add(vkv, wp.tile_sum(wp.tile(k_part)), offset=at[0])
    wp.tile_atomic_add(vmv, wp.tile_sum(wp.tile(m_part)), offset=at[0])
    block = wp.tile_max(wp.tile(top))
    if top == block[0]:  # the block's largest (each thread its own on the CPU, whose tiles hold one lane)
        wp.atomic_max(largest, at[0], top)


@wp.kernel
def normalise_iterate(w: wp.array(dtype=wp.vec3), largest: wp.array(dtype=float), n_nodes: int,
                      v: wp.array(dtype=wp.vec3)):
    """v = w / max|w| per model."""
    i = wp.tid()
    scale = largest[i % largest.shape[0]]
    if scale > 0.0:
        v[i] = w[i] / scale


@wp.kernel
def stable_steps(vkv: wp.array(dtype=float), vmv: wp.array(dtype=float), smallest: wp.float64,
                 stable: wp.array(dtype=wp.float64)):
    """The stable step 2 / omega (s) per model from the power iteration's terms, omega^2 =
    v^T K v / max(v^T M v, ``smallest``); inf where no stiffness was seen."""
    b = wp.tid()
    quotient = wp.float64(vkv[b]) / wp.max(wp.float64(vmv[b]), smallest)
    step = wp.float64(wp.inf)
    if quotient > wp.float64(0.0):
        step = wp.float64(2.0) / wp.sqrt(quotient)
    stable[b] = step


@wp.kernel
def keep_step_stable(stable_now: wp.array(dtype=wp.float64), inverted: wp.array(dtype=int), dt: wp.float64,
                     above: wp.float64, to: wp.float64, stable: wp.array(dtype=wp.float64),
                     grow: wp.array(dtype=wp.float64), growth: wp.array(dtype=wp.float64),
                     rescales: wp.array(dtype=int)):
    """Mass scaling's rule, one thread per model (see :class:`BreastBiomechLib.solver.stability.MassScaling`):
    where the step ``dt`` (s) exceeds ``above`` x the stable step of any model still moving (no
    inverted element, not converged: a model at rest sets no other's masses), model b's masses are
    to grow by ``grow[b]`` = max((dt / (``to`` x its stable step))^2, 1) (1 otherwise), its total
    ``growth`` and ``rescales`` follow, and ``stable`` is its stable step after."""
    b = wp.tid()
    rescale = int(0)
    for c in range(stable_now.shape[0]):
        if inverted[4 * c] == 0 and inverted[4 * c + 3] == 0 and not (dt <= above * stable_now[c]):
            rescale = 1
    mine = stable_now[b]
    if inverted[4 * b] != 0:
        mine = wp.float64(wp.inf)
    g = wp.float64(1.0)
    if rescale != 0:
        ratio = dt / (to * mine)
        g = wp.max(ratio * ratio, wp.float64(1.0))
        growth[b] = growth[b] * g
        rescales[b] = rescales[b] + 1
    grow[b] = g
    stable[b] = mine * wp.sqrt(g)


@wp.kernel
def grow_masses(grow: wp.array(dtype=wp.float64), mass_float64: wp.array(dtype=wp.float64),
                mass: wp.array(dtype=float)):
    """Node-model i's mass times its model's ``grow`` (see :func:`keep_step_stable`), kept in
    float64 and rounded once into the steps' float32 ``mass``."""
    i = wp.tid()
    g = grow[i % grow.shape[0]]
    if g != wp.float64(1.0):
        m = mass_float64[i] * g
        mass_float64[i] = m
        mass[i] = float(m)


@wp.kernel
def zero_constrained(v: wp.array(dtype=wp.vec3), nodes: wp.array(dtype=int), mask: wp.array(dtype=wp.vec3),
                     n_nodes: int, n_constrained: int):
    """Zero the prescribed components of v: they take no part in the dynamics."""
    tid = wp.tid()
    b = tid // n_constrained
    i = nodes[tid - b * n_constrained] * (v.shape[0] // n_nodes) + b
    m = mask[tid - b * n_constrained]
    x = v[i]
    v[i] = wp.vec3(wp.where(m[0] > 0.0, 0.0, x[0]), wp.where(m[1] > 0.0, 0.0, x[1]), wp.where(m[2] > 0.0, 0.0, x[2]))


@wp.kernel
def support_springs(u: wp.array(dtype=wp.vec3), nodes: wp.array(dtype=int), normals: wp.array(dtype=wp.vec3),
                    stiffness: wp.array(dtype=wp.vec2), n_models: int, models: wp.array(dtype=int),
                    n_listed: int, forces: wp.array2d(dtype=float)):
    """Springs of a surface support added to the internal forces: k_n (u.n) n + k_t (u - (u.n) n)
    at each supported node, ``stiffness[k]`` = (k_n, k_t) in N/m (the stiffness per area times
    the node's area), n its surface normal, for the listed ``models`` (see the module's docstring)."""
    at = listed(models, n_listed, n_models, wp.tid())
    k, b = at[0], at[1]
    if k < 0 or k >= nodes.shape[0]:
        return
    i = nodes[k] * n_models + b
    n = normals[k]
    along = wp.dot(u[i], n) * n
    add_force(forces, i, stiffness[k][0] * along + stiffness[k][1] * (u[i] - along))
