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

from BreastBiomechLib.solver.model import Constraint


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
