"""Per-model sums and the sample's kernels: energies, plate forces, the relaxation's Rayleigh-quotient
terms, the largest nodal change, the stable-step power iteration and mass scaling. SI units.
"""

from __future__ import annotations

import warp as wp

from BreastBiomechLib.solver.kernels.common import MaterialTable, force_at, material_of
from BreastBiomechLib.solver.kernels.element import deformation_gradient, strain_energy_density

wp.set_module_options({"fast_math": True})  # as every module of this package (why: common.py)


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
