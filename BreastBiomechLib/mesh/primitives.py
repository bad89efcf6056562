"""Simple tetrahedral meshes for verification: boxes split into Kuhn tetrahedra.

Coordinates in millimetres (LPS axes)."""

from __future__ import annotations

from itertools import permutations

import numpy as np

from BreastBiomechLib.mesh.tetmesh import TetMesh


def box_mesh(size_mm, divisions, origin_mm=(0.0, 0.0, 0.0)) -> TetMesh:
    """An axis-aligned box of ``size_mm`` (3,) split into ``divisions`` (3,) cubes, each cut into
    the six Kuhn tetrahedra around its main diagonal (a conforming mesh). Point data
    ``face_<axis><lo|hi>`` marks the nodes on each face (uint8)."""
    size = np.asarray(size_mm, float)
    n = np.asarray(divisions, int)
    if np.any(n < 1) or np.any(size <= 0):
        raise ValueError("box_mesh needs positive sizes and at least one division per axis")
    axes = [np.linspace(0.0, size[i], n[i] + 1) + origin_mm[i] for i in range(3)]
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    nodes = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
    index = np.arange(len(nodes)).reshape(n[0] + 1, n[1] + 1, n[2] + 1)
    i, j, kk = np.meshgrid(np.arange(n[0]), np.arange(n[1]), np.arange(n[2]), indexing="ij")
    i, j, kk = i.ravel(), j.ravel(), kk.ravel()
    tets = []
    for order in permutations(range(3)):
        corner = np.zeros((len(i), 3), int)
        path = [corner.copy()]
        for axis in order:
            corner[:, axis] += 1
            path.append(corner.copy())
        tets.append(np.stack([index[i + c[:, 0], j + c[:, 1], kk + c[:, 2]] for c in path], axis=1))
    tets = np.concatenate(tets)
    mesh = TetMesh(nodes, tets)
    negative = mesh.volumes < 0
    tets[negative] = tets[negative][:, [0, 2, 1, 3]]
    point_data = {}
    for a, name in enumerate("xyz"):
        point_data[f"face_{name}lo"] = np.isclose(nodes[:, a], axes[a][0]).astype(np.uint8)
        point_data[f"face_{name}hi"] = np.isclose(nodes[:, a], axes[a][-1]).astype(np.uint8)
    return TetMesh(nodes, tets, point_data=point_data)
