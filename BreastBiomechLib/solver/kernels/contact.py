"""Constraints, supports and plate contact: the records the node kernel reads
(:class:`NodeConstraints`, :class:`PlatePose`, :class:`PlateContact`), a node's contact with a
plate (:func:`touch_plate`), support springs and the zeroing of constrained components. SI units.
"""

from __future__ import annotations

import warp as wp

from BreastBiomechLib.solver.kernels.common import NodeState, add_force, clipped, listed

wp.set_module_options({"fast_math": True})  # as every module of this package (why: common.py)


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
