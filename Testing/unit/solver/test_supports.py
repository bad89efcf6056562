"""Supports: a fixed node set plus the patches that stop rigid motion, and the instability they
prevent (a compressed breast turning between frictionless plates)."""

from __future__ import annotations

import numpy as np
import pytest

from BreastBiomechLib.mesh.primitives import hemi_ellipsoid_mesh
from BreastBiomechLib.solver.supports import support_constraints


@pytest.fixture(scope="module")
def chest():
    mesh = hemi_ellipsoid_mesh((50.0, 40.0, 45.0), 5.0)
    return mesh.nodes, np.flatnonzero(mesh.point_data["chest_wall"])


def _rigid_motions_left(positions, constraints):
    """Dimension of the rigid motions (3 translations, 3 rotations about the origin) that satisfy
    every constraint: the null space of the constrained components of the rigid-motion basis."""
    rows = []
    for c in constraints:
        for node, mask in zip(c.nodes, c.mask):
            x = positions[node]
            basis = np.hstack([np.eye(3), -np.array([[0, -x[2], x[1]], [x[2], 0, -x[0]], [-x[1], x[0], 0]])])
            rows.extend(basis[mask])
    return 6 - np.linalg.matrix_rank(np.array(rows), tol=1e-9)


def test_anchor_patches_remove_every_rigid_motion(chest):
    positions, nodes = chest
    sliding = support_constraints(positions, nodes, (False, True, False), anchor=False)
    assert _rigid_motions_left(positions, sliding) == 3  # two translations in the plane, one turn
    one_point = sliding + [support_constraints(positions, nodes, (False, True, False), anchor_radius_mm=0.0)[1]]
    assert _rigid_motions_left(positions, one_point) == 1  # a single anchor node still lets it turn
    full = support_constraints(positions, nodes, (False, True, False))
    assert _rigid_motions_left(positions, full) == 0
    centre_patch, far_patch = full[1], full[2]
    assert 1 < len(centre_patch.nodes) < len(nodes) and centre_patch.mask.all()
    assert far_patch.mask[:, 0].all() and not far_patch.mask[:, 1:].any()  # held left-right only
    assert np.abs(positions[far_patch.nodes, 2]).min() > 30.0  # at the superior or inferior end
    # fixed in two directions: one free direction, the centre patch is enough
    two = support_constraints(positions, nodes, (True, True, False))
    assert len(two) == 2 and _rigid_motions_left(positions, two) == 0


def test_bad_supports_are_refused(chest):
    positions, nodes = chest
    with pytest.raises(ValueError, match="at least one direction"):
        support_constraints(positions, nodes, (False, False, False))
    with pytest.raises(ValueError, match="empty"):
        support_constraints(positions, [], (False, True, False))
    line = nodes[np.abs(positions[nodes, 2]) < 1e-9]
    with pytest.raises(ValueError, match="too narrow"):
        support_constraints(positions, line, (False, True, False))
