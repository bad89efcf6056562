"""The kernels' shared pieces: load curves, the list of models a launch computes, nodal force planes,
the material table, ANP modes, a node's state and the specialised kernels' build options. SI units.
"""

from __future__ import annotations

import warp as wp

# CUDA builds of this module use fast math (approximate division, square root and powers, denormals
# flushed; no reassociation, so the compensated displacement sum holds): the element kernel's
# divisions and powers are a good part of its time, and a step costs 12-13 % less at 160k tets and
# in batches of 64, 7 % less at 2M (H200, docs/benchmarks.md). warp's CPU builds ignore the option:
# CPU results are unchanged. Every module of this package sets it.
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


ANP_WITHIN_MATERIALS = wp.constant(1)  # a slot per node and bulk modulus (host_setup.anp_slots)


ANP_ACROSS_MATERIALS = wp.constant(2)  # a slot per node, whatever its elements' materials (NiftySim's)


# the specialised element kernels' options: a module of their own each (fast math as this module's)
SPECIALISED = {"module": "unique", "module_options": {"fast_math": True}}


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
class NodeState:
    """One node's displacement ``u`` (m), its float32 rounding remainder ``low`` (see
    :func:`advance_nodes`) and its last increment ``du`` (m), held in registers while a step
    updates them."""
    u: wp.vec3
    du: wp.vec3
    low: wp.vec3
