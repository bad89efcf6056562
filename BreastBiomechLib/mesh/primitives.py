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


def hemi_ellipsoid_mesh(radii_mm=(80.0, 70.0, 75.0), spacing_mm: float = 5.0) -> TetMesh:
    """A breast-like half ellipsoid on the chest-wall plane y = 0, pointing anteriorly (-y):
    x^2/a^2 + y^2/d^2 + z^2/b^2 <= 1, y <= 0, with ``radii_mm`` = (a, d, b). Built from a Kuhn
    grid of cubes of ``spacing_mm`` keeping the cubes whose centre is inside (a stair-stepped
    surface: meant for verification and benchmarks, not anatomy). Point data ``chest_wall``
    marks the nodes on y = 0 and ``surface`` the other boundary nodes."""
    a, d, b = (float(r) for r in radii_mm)
    n = np.ceil(np.array([2 * a, d, 2 * b]) / spacing_mm).astype(int)
    size = n * spacing_mm
    box = box_mesh(size, n, origin_mm=(-size[0] / 2, -size[1], -size[2] / 2))
    centres = box.nodes[box.tets].mean(axis=1)
    # cube centre of each tet: the six tets of a cube share it; use the tet centroid's cube
    cube = np.floor((centres - box.nodes.min(axis=0)) / spacing_mm)
    cube_centre = box.nodes.min(axis=0) + (cube + 0.5) * spacing_mm
    inside = (cube_centre[:, 0] / a) ** 2 + (cube_centre[:, 1] / d) ** 2 + (cube_centre[:, 2] / b) ** 2 <= 1.0
    tets = box.tets[inside]
    used, new_tets = np.unique(tets, return_inverse=True)
    nodes = box.nodes[used]
    tets = new_tets.reshape(-1, 4)
    faces = np.sort(np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 2, 3]], tets[:, [0, 1, 3]], tets[:, [0, 1, 2]]]), axis=1)
    unique_faces, counts = np.unique(faces, axis=0, return_counts=True)
    boundary = np.zeros(len(nodes), bool)
    boundary[unique_faces[counts == 1].ravel()] = True
    chest = np.isclose(nodes[:, 1], 0.0)
    return TetMesh(nodes, tets, point_data={"chest_wall": chest.astype(np.uint8),
                                            "surface": (boundary & ~chest).astype(np.uint8)})
