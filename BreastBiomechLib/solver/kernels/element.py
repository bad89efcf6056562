"""Element kernels: the deformation gradient, the hyperelastic and visco stresses, ANP's nodal
pressure pass and the element forces (:func:`element_kernels`, built per formulation). SI units.
"""

from __future__ import annotations

import collections
import functools

import warp as wp

from BreastBiomechLib.solver.kernels.common import (ANP_ACROSS_MATERIALS, ANP_OFF, SPECIALISED, ElementMaterial,
                                                    MaterialTable, add_force, element_and_lane, listed, material_of,
                                                    model_at)

wp.set_module_options({"fast_math": True})  # as every module of this package (why: common.py)


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
    its own copy of these lines, see :func:`model_element_stress`)."""
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
    """Count an inverted element of model b, keeping the first one found and its step. Called by
    the force kernels in their own bodies, not by :func:`element_first_piola`: inlined there its
    atomic and stores cost the lone model's step 6-9 %, out of line (a call) 2-3 % (160k and 2M
    tets, H100 and H200, 2026-12-05; docs/benchmarks.md)."""
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
def element_first_piola(F: wp.mat33, m: ElementMaterial, mean: float, anp: int, v0: float, e: int, b: int,
                        n_models: int, n_terms: int, prony_g: wp.array(dtype=float),
                        prony_decay: wp.array(dtype=float), visco_state: wp.array(dtype=wp.mat33),
                        update_state: int):
    """The element force's stress, V0 P (N m), of element e of model b at deformation gradient
    ``F``: with ANP (``anp`` not :data:`ANP_OFF`) F is scaled to the dilatation Jm of ``mean``,
    the mean of the averaged pressures at the element's slots, as NiftySim's T4ANP (Jm - 1 the mean
    of the slots' volume changes per volume within materials; across them, the mean pressure over
    kappa_e). Visco terms (``n_terms`` per element): S = S_vol + S_iso - sum_i g_i Q_i with
    dQ_i/dt = (S_iso - Q_i) / tau_i, integrated exactly for a stress constant over the step
    (Q_i <- d_i Q_i + (1 - d_i) S_iso, d_i = exp(-dt / tau_i)) when ``update_state`` is set. An
    element with J <= 0 (or Jm <= 0) gives (0, 0), any other (V0 P, 1): the caller records the
    inversion (:func:`record_inversion`) and its model is frozen from then on. The one body of the element force, for both element
    kernels."""
    cof = cofactor(F)
    J = F[0, 0] * cof[0, 0] + F[0, 1] * cof[0, 1] + F[0, 2] * cof[0, 2]
    if J <= 0.0:
        return wp.mat33(0.0), 0
    Jm = J
    scale = float(1.0)
    if anp != ANP_OFF:
        # across materials the sums are pressures; within, volume changes (divided by 1, exactly)
        Jm = mean / wp.where(anp == ANP_ACROSS_MATERIALS, m.kappa, 1.0) + 1.0
        if Jm <= 0.0:
            return wp.mat33(0.0), 0
        scale = wp.pow(Jm / J, 1.0 / 3.0)
    if n_terms > 0:
        j = e * n_models + b  # the element's entry of model b (visco state)
        return visco_first_piola(scale * F, Jm, m.mu, m.kappa, m.eta, m.fibre, v0, j * n_terms, n_terms, prony_g,
                                 prony_decay, visco_state, update_state), 1
    return scaled_first_piola(F, cof, J, Jm, scale, m.mu, m.kappa, m.eta, m.fibre, v0), 1


@wp.func
def hand_on_step(clock: wp.array(dtype=int), tid: int):
    """The step's number ``clock[0]`` copied to ``clock[1]`` by thread 0 of a force kernel, for
    :func:`advance_nodes`, which advances it."""
    if tid == 0:
        clock[1] = clock[0]


@wp.func
def add_element_forces(forces: wp.array2d(dtype=float), n_models: int, b: int, n0: int, n1: int, n2: int, n3: int,
                       P: wp.mat33, d0: wp.vec3, d1: wp.vec3, d2: wp.vec3, d3: wp.vec3):
    """Element forces f_a = V0 P dN_a/dX (``P`` from :func:`element_first_piola`) added at the
    element's nodes of model b."""
    add_force(forces, n0 * n_models + b, P * d0)
    add_force(forces, n1 * n_models + b, P * d1)
    add_force(forces, n2 * n_models + b, P * d2)
    add_force(forces, n3 * n_models + b, P * d3)


@wp.func
def model_element_stress(u: wp.array(dtype=wp.vec3), e: int, b: int, n_models: int, n0: int, n1: int, n2: int,
                         n3: int, d0: wp.vec3, d1: wp.vec3, d2: wp.vec3, d3: wp.vec3, v0: float, frozen: int,
                         materials: MaterialTable, anp: int, tets: wp.array2d(dtype=int),
                         slots: wp.array2d(dtype=int), slots_are_nodes: int, slot_volume: wp.array(dtype=float),
                         anp_sums: wp.array(dtype=float), n_terms: int, prony_g: wp.array(dtype=float),
                         prony_decay: wp.array(dtype=float), visco_state: wp.array(dtype=wp.mat33),
                         update_state: int):
    """(V0 P (N m), whole) of element e of model b (:func:`element_first_piola`; whole 0: the
    element is inverted, the caller records it), given the element's nodes,
    shape derivatives ``d0``-``d3``, volume ``v0`` and its model's ``frozen`` flag (read by the
    caller first, with the element's reads, so that they are in flight together): the element's
    material and ANP mean are read here, and a frozen model's element gives zero and touches no
    state (whole 1; the caller adds no forces for it). The element force of both element kernels: the lone
    :func:`element_forces` reads the element itself, a thread per element and model (built on a
    per-model function of the whole force its lone 2M-tet step took 170-173 us against 163-165;
    H200, 2026-12-01, docs/benchmarks.md); :func:`element_forces_shared` reads it once for a
    thread's models."""
    m = material_of(materials, e, n_models, b)
    mean = float(0.0)  # of the slots' sums per volume
    if anp != ANP_OFF:
        mean = mean_slot_change(anp_sums, slot_volume, element_slots(tets, slots, slots_are_nodes, e), b, n_models)
    F = deformation_gradient(u, b, n_models, n0, n1, n2, n3, d0, d1, d2, d3)
    if frozen != 0:
        return wp.mat33(0.0), 1
    return element_first_piola(F, m, mean, anp, v0, e, b, n_models, n_terms, prony_g, prony_decay, visco_state,
                               update_state)


ElementKernels = collections.namedtuple("ElementKernels", "nodal_pressure nodal_pressure_shared element_forces "
                                                         "element_forces_shared")


@functools.cache
def element_kernels(anp_mode: int, visco: bool, node_slots: bool) -> ElementKernels:
    """The element kernels for one formulation: ANP mode ``anp_mode`` (``ANP_*``), Prony terms
    (``visco``) or none, and ANP slots that are the elements' nodes (``node_slots``, see
    :func:`element_slots`) or a table of their own, as compile-time constants, so that a kernel
    holds only its formulation's arithmetic, branches and registers (the batch element kernel 803
    static instructions and 80 registers against 1 229 and 96 built for every formulation; batches
    of 64 and 16 models 10 % faster, a lone 2M-tet model 3 %; H200, docs/benchmarks.md). Each
    combination is compiled once, on its first launch, in a warp module of its own."""

    @wp.kernel(name="nodal_pressure", **SPECIALISED)
    def nodal_pressure(u: wp.array(dtype=wp.vec3), tets: wp.array2d(dtype=int), slots: wp.array2d(dtype=int),
                       dhdx: wp.array2d(dtype=wp.vec3), vol0: wp.array(dtype=float),
                       materials: MaterialTable, n_models: int, models: wp.array(dtype=int), n_listed: int,
                       anp_sums: wp.array(dtype=float)):
        """ANP pass 1: accumulate each element's volume change (J_e - 1) V_e (m^3) at its ANP slots
        (:func:`element_slots`), for the listed ``models`` (see the module's docstring; converged
        models stand still). With ``anp`` = :data:`ANP_WITHIN_MATERIALS` each slot gathers the
        elements of one node and one bulk modulus (:func:`BreastBiomechLib.solver.host_setup.anp_slots`):
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
        """Internal nodal forces f_a = V0 F S dN_a/dX (the stress: :func:`element_first_piola`, with
        ANP from :func:`nodal_pressure`'s sums; visco terms ``n_terms`` per element). Elements with
        J <= 0 are counted per model, the first one and its step in ``inverted[4b:4b+4]`` = [count,
        element, step, frozen] of model b; once frozen (1; 2 for a model a relaxation has found
        converged, :mod:`BreastBiomechLib.solver.relaxation`) that model stands still, keeping its
        last configuration instead of producing NaN, while the others go on. Only the listed
        ``models`` are computed (see the module's docstring). The step is ``clock[0]``, copied to
        ``clock[1]`` for :func:`advance_nodes`, which advances it."""
        anp = wp.static(anp_mode)  # constants of this specialisation (see element_kernels)
        slots_are_nodes = wp.static(int(node_slots))
        terms = n_terms * wp.static(int(visco))  # no Prony terms: 0, a constant
        tid = wp.tid()
        hand_on_step(clock, tid)
        at = listed(models, n_listed, n_models, tid)
        e, b = at[0], at[1]
        if e < 0 or e >= tets.shape[0]:
            return
        frozen = inverted[4 * b + 3]  # first: in flight with the element's reads (see model_element_stress)
        n0, n1, n2, n3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
        d0, d1, d2, d3 = dhdx[e, 0], dhdx[e, 1], dhdx[e, 2], dhdx[e, 3]
        P, whole = model_element_stress(u, e, b, n_models, n0, n1, n2, n3, d0, d1, d2, d3, vol0[e], frozen,
                                        materials, anp, tets, slots, slots_are_nodes, slot_volume, anp_sums, terms,
                                        prony_g, prony_decay, visco_state, update_state)
        if frozen != 0:
            return
        if whole == 0:
            record_inversion(inverted, b, e, clock[0])
            return
        add_element_forces(forces, n_models, b, n0, n1, n2, n3, P, d0, d1, d2, d3)

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
        terms = n_terms * wp.static(int(visco))  # no Prony terms: 0, a constant
        tid = wp.tid()
        hand_on_step(clock, tid)
        at = element_and_lane(lanes, tid)
        e = at[0]
        if e >= tets.shape[0]:
            return
        n0, n1, n2, n3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
        d0, d1, d2, d3, v0 = dhdx[e, 0], dhdx[e, 1], dhdx[e, 2], dhdx[e, 3], vol0[e]
        entry = at[1]
        while entry < n_listed:
            b = model_at(models, n_listed, n_models, entry)
            frozen = inverted[4 * b + 3]
            P, whole = model_element_stress(u, e, b, n_models, n0, n1, n2, n3, d0, d1, d2, d3, v0, frozen,
                                            materials, anp, tets, slots, slots_are_nodes, slot_volume, anp_sums,
                                            terms, prony_g, prony_decay, visco_state, update_state)
            if frozen == 0:
                if whole == 0:
                    record_inversion(inverted, b, e, clock[0])
                else:
                    add_element_forces(forces, n_models, b, n0, n1, n2, n3, P, d0, d1, d2, d3)
            entry += lanes

    return ElementKernels(nodal_pressure, nodal_pressure_shared, element_forces, element_forces_shared)
