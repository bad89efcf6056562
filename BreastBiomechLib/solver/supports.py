"""Supports: a node set (e.g. the chest wall) fixed in some directions, and the extra nodes that
keep the model from moving as a rigid body in the others.

The seed fixes the pectoral surface nodes anterior-posteriorly and one node in a second
direction. A chest wall fixed only in its normal direction still lets the breast translate in
the two tangential directions and rotate about the normal; one node fixed in those directions
stops the translations but not the rotation. Between frictionless plates the rotation is a real
instability when the breast is wider along the compression axis than across it (the compressed
breast lowers its energy by turning, which a long physical-time run does after a few seconds),
so a second node, far from the first, is fixed against it. Positions in LPS mm.
"""

from __future__ import annotations

import numpy as np

from BreastBiomechLib.mesh.tetmesh import boundary_faces
from BreastBiomechLib.solver.model import Constraint, SurfaceSupport


def support_constraints(positions: np.ndarray, nodes, components=(False, True, False),
                        anchor: bool = True, anchor_radius_mm: float = 10.0) -> list[Constraint]:
    """``nodes`` fixed in ``components`` (x, y, z), and with ``anchor`` the rigid motions this
    leaves removed: the support nodes within ``anchor_radius_mm`` of the one nearest the set's
    centre fixed in every direction and, when two directions are free, those within the radius
    of the node farthest from it along the second free axis fixed in the first (no rotation about
    the fixed axis). With the chest wall fixed anterior-posteriorly that second patch is the most
    superior or inferior part held left-right, which a medio-lateral compression barely moves that
    way. Patches, not single nodes: a point support has no stiffness in the continuum limit, so a
    one-node anchor gets softer with every refinement and the model's tangential sliding
    converges ever more slowly (at 160k tets a physical-time run still drifted by 0.6 mm between
    4 and 8 s of settling). ``positions`` are all mesh nodes (N, 3) mm."""
    nodes = np.unique(np.asarray(nodes, dtype=np.int64).ravel())
    fixed = np.asarray(components, bool).reshape(3)
    if len(nodes) == 0:
        raise ValueError("the support node set is empty")
    if not fixed.any():
        raise ValueError("fix the support nodes in at least one direction")
    if anchor_radius_mm < 0:
        raise ValueError("the anchor radius must be >= 0 mm")
    constraints = [Constraint.fixed(nodes, fixed)]
    free = np.flatnonzero(~fixed)
    if not anchor or len(free) == 0:
        return constraints
    p = positions[nodes]

    def patch(index: int) -> np.ndarray:
        return nodes[np.linalg.norm(p - positions[index], axis=1) <= anchor_radius_mm]

    centre = nodes[np.argmin(np.linalg.norm(p - p.mean(axis=0), axis=1))]
    constraints.append(Constraint.fixed(patch(centre)))
    if len(free) == 2:
        across, along = free
        far = nodes[np.argmax(np.abs(p[:, along] - positions[centre, along]))]
        if abs(positions[far, along] - positions[centre, along]) <= anchor_radius_mm:
            raise ValueError("the support nodes are too narrow across the free directions to stop the model "
                             "from turning; fix them in more directions")
        constraints.append(Constraint.fixed(patch(far), np.eye(3, dtype=bool)[across]))
    return constraints


SUPPORT_KINDS = ("fixed", "sliding", "elastic")


def surface_normals_and_areas(mesh, nodes) -> tuple[np.ndarray, np.ndarray]:
    """Each of ``nodes``' (boundary node ids) unit outward surface normal and the surface area
    it stands for (mm^2): a third of each boundary face whose three nodes are all in the set
    (area-weighted normals of those faces; for a node at the set's rim with no such face, of
    the boundary faces around it)."""
    nodes = np.unique(np.asarray(nodes, dtype=np.int64).ravel())
    faces, _ = boundary_faces(mesh.tets)
    p = mesh.nodes[faces]
    area_vectors = 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    in_set = np.zeros(len(mesh.nodes), bool)
    in_set[nodes] = True
    inside = in_set[faces].all(axis=1)
    normal_sum = np.zeros((len(mesh.nodes), 3))
    area = np.zeros(len(mesh.nodes))
    for corner in range(3):
        np.add.at(normal_sum, faces[inside, corner], area_vectors[inside])
        np.add.at(area, faces[inside, corner], np.linalg.norm(area_vectors[inside], axis=1) / 3.0)
    rim = nodes[np.linalg.norm(normal_sum[nodes], axis=1) == 0]
    if len(rim):
        touching = np.isin(faces, rim).any(axis=1)
        for corner in range(3):
            np.add.at(normal_sum, faces[touching, corner], area_vectors[touching])
    normals = normal_sum[nodes]
    length = np.linalg.norm(normals, axis=1)
    if np.any(length == 0):
        bad = nodes[length == 0][:5]
        raise ValueError(f"nodes {bad.tolist()} of the support lie on no boundary face; a surface support needs "
                         "surface nodes (e.g. the chest_wall node set)")
    return normals / length[:, None], area[nodes]


def chest_wall_support(mesh, nodes, kind: str = "fixed", components=(False, True, False),
                       normal_stiffness: float = 0.0, tangential_stiffness: float = 0.0,
                       anchor: bool = True, held_by: str = "") -> tuple[list, list, str]:
    """The chest wall's boundary condition, as (constraints, surface supports, a sentence saying
    what holds the model). ``kind``:

    - "fixed": the seed's and today's default, ``nodes`` fixed in ``components`` with the anchor
      patches of :func:`support_constraints` against the rigid motions this leaves;
    - "sliding": zero displacement along the local chest-surface normal, free along the surface
      or held by ``tangential_stiffness`` (Pa/mm, per area);
    - "elastic": springs of ``normal_stiffness`` (> 0) and ``tangential_stiffness`` (Pa/mm).

    Along a surface with no tangential stiffness the model could still move as a rigid body
    (slide and turn on the chest); with ``anchor`` the patches of :func:`support_constraints` are
    held along it (the coordinate axes other than the one the wall faces) at the chest wall's
    centre and in one of them at its far end, and the sentence says so. Without anchor and without tangential stiffness it is refused.
    ``mesh`` (TetMesh, LPS mm); ``nodes`` the chest-wall node ids."""
    nodes = np.unique(np.asarray(nodes, dtype=np.int64).ravel())
    if kind not in SUPPORT_KINDS:
        raise ValueError(f"the chest-wall support is one of {SUPPORT_KINDS}, not {kind!r}")
    if kind == "fixed":
        constraints = support_constraints(mesh.nodes, nodes, components, anchor=anchor)
        axes = "".join(a for a, c in zip("xyz", components) if c) or "none"
        held = (f"; rigid motion stopped by {sum(len(c.nodes) for c in constraints[1:])} anchor nodes"
                if len(constraints) > 1 else "")
        return constraints, [], f"chest wall fixed in {axes} ({len(nodes)} nodes){held}"
    if kind == "elastic" and not normal_stiffness > 0:
        raise ValueError("an elastic chest wall needs a normal stiffness > 0 (Pa/mm); with none it is sliding")
    normals, areas = surface_normals_and_areas(mesh, nodes)
    support = SurfaceSupport(nodes, normals, areas, kind, normal_stiffness, tangential_stiffness)
    springs = (f"springs {normal_stiffness:g} Pa/mm across, {tangential_stiffness:g} Pa/mm along" if kind == "elastic"
               else f"sliding on its surface{f', held along it by {tangential_stiffness:g} Pa/mm' if tangential_stiffness else ''}")
    sentence = f"chest wall {springs} ({len(nodes)} nodes, {areas.sum():.0f} mm^2)"
    if tangential_stiffness > 0:
        return [], [support], sentence + "; the tangential springs stop rigid motion"
    if not anchor and held_by:
        return [], [support], f"{sentence}; rigid motion stopped by {held_by}"
    if not anchor:
        raise ValueError(f"a {kind} chest wall without tangential stiffness leaves the model free to slide and turn "
                         "on it; give a tangential stiffness (Pa/mm) or keep the anchor patches")
    mean_normal = normals.mean(axis=0)
    across = np.eye(3, dtype=bool)[int(np.argmax(np.abs(mean_normal)))]  # the axis the wall faces
    # the anchor patches only, held along the surface (across it the support holds them)
    constraints = support_constraints(mesh.nodes, nodes, across, anchor=True)[1:]
    constraints[0] = Constraint.fixed(constraints[0].nodes, ~across)
    return constraints, [support], (f"{sentence}; rigid motion along it stopped by fixing "
                                    f"{', '.join(f'{len(c.nodes)} nodes in {_axes(c.mask[0])}' for c in constraints)} "
                                    "(the anchor patches at its centre and far end)")


def _axes(mask) -> str:
    return "".join(a for a, c in zip("xyz", mask) if c)
