"""Simple tetrahedral meshes for verification: boxes split into Kuhn tetrahedra.

Coordinates in millimetres (LPS axes)."""

from __future__ import annotations

from itertools import permutations

import numpy as np

from BreastBiomechLib.mesh.refine import refine_uniform
from BreastBiomechLib.mesh.tetmesh import TetMesh, boundary_nodes, signed_volumes


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


def hemi_ellipsoid_mesh(radii_mm=(80.0, 70.0, 75.0), spacing_mm: float = 5.0, pull_corners: bool = False) -> TetMesh:
    """A breast-like half ellipsoid on the chest-wall plane y = 0, pointing anteriorly (-y):
    x^2/a^2 + y^2/d^2 + z^2/b^2 <= 1, y <= 0, with ``radii_mm`` = (a, d, b). Built from a Kuhn
    grid of cubes of ``spacing_mm`` keeping the cubes whose centre is inside (a stair-stepped
    surface: meant for verification and benchmarks, not anatomy). ``pull_corners``: the boundary
    nodes outside the ellipsoid (the stairs' protruding corners) are moved onto it along the ray
    from its centre, but for those whose move would flatten one of their elements under a tenth
    of its volume; the others stay (the same elements; under a plate's rounded edge a
    protruding corner is pushed into its own cube and inverts it, which a mesh of a smooth
    surface does not do). Point data ``chest_wall`` marks the nodes on y = 0 and ``surface`` the
    other boundary nodes."""
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
    boundary = boundary_nodes(tets, len(nodes))
    chest = np.isclose(nodes[:, 1], 0.0)
    if pull_corners:
        nodes = _pulled_corners(nodes, tets, boundary, (a, d, b))
    return TetMesh(nodes, tets, point_data={"chest_wall": chest.astype(np.uint8),
                                            "surface": (boundary & ~chest).astype(np.uint8)})


def _pulled_corners(nodes: np.ndarray, tets: np.ndarray, boundary: np.ndarray, radii, floor: float = 0.1) -> np.ndarray:
    """``nodes`` with the ``boundary`` nodes outside the ellipsoid of ``radii`` (centred at the
    origin) moved onto it along the ray from the centre, except where that would leave one of
    their elements under ``floor`` x its volume (a sliver): those nodes stay (mm)."""
    q = ((nodes / np.asarray(radii, float)) ** 2).sum(axis=1)
    pulled = boundary & (q > 1.0)
    target = nodes.copy()
    target[pulled] /= np.sqrt(q[pulled])[:, None]

    before = signed_volumes(nodes, tets)
    while True:
        moved = np.where(pulled[:, None], target, nodes)
        thin = signed_volumes(moved, tets) < floor * before
        if not thin.any():
            return moved
        back = np.zeros(len(nodes), bool)
        back[tets[thin].ravel()] = True
        pulled &= ~back


def _zip_rings(a: np.ndarray, a_angles: np.ndarray, b: np.ndarray, b_angles: np.ndarray) -> list:
    """Triangles joining two closed rings of point ids ordered by angle (rad)."""
    if len(a) == 1 or len(b) == 1:
        centre, ring = (a[0], b) if len(a) == 1 else (b[0], a)
        return [(centre, ring[i], ring[(i + 1) % len(ring)]) for i in range(len(ring))]
    triangles, i, j = [], 0, 0
    while i < len(a) or j < len(b):
        next_a = a_angles[i + 1] if i + 1 < len(a) else a_angles[0] + 2 * np.pi
        next_b = b_angles[j + 1] if j + 1 < len(b) else b_angles[0] + 2 * np.pi
        if j >= len(b) or (i < len(a) and next_a <= next_b):
            triangles.append((a[i % len(a)], a[(i + 1) % len(a)], b[j % len(b)]))
            i += 1
        else:
            triangles.append((a[i % len(a)], b[(j + 1) % len(b)], b[j % len(b)]))
            j += 1
    return triangles


def _half_ball_surface(edge: float) -> tuple[np.ndarray, np.ndarray]:
    """Closed triangulated surface of the unit half ball y <= 0 (dome + chest disc), triangles of
    edge length about ``edge`` (unit radius)."""
    rings_dome = max(2, int(np.ceil(0.5 * np.pi / edge)))
    rings_disc = max(2, int(np.ceil(1.0 / edge)))
    points, rings = [], []

    def add_ring(radius, y, offset):
        count = 1 if radius < 1e-12 else max(6, int(round(2 * np.pi * radius / edge)))
        angles = 2 * np.pi * (np.arange(count) + offset) / count
        ids = np.arange(len(points), len(points) + count)
        points.extend(np.c_[radius * np.cos(angles), np.full(count, y), radius * np.sin(angles)])
        rings.append((ids, angles))

    for k in range(rings_dome + 1):  # apex (-y) to the rim
        phi = 0.5 * np.pi * k / rings_dome
        add_ring(np.sin(phi), -np.cos(phi) if k < rings_dome else 0.0, 0.5 * (k % 2))
    for j in range(rings_disc - 1, -1, -1):  # chest disc, rim inwards to its centre
        add_ring(j / rings_disc, 0.0, 0.5 * (j % 2))
    triangles = []
    for (a, aa), (b, ba) in zip(rings[:-1], rings[1:]):
        triangles += _zip_rings(a, aa, b, ba)
    return np.array(points), np.array(triangles, dtype=np.int32)


def smooth_hemi_ellipsoid_mesh(radii_mm=(80.0, 70.0, 75.0), edge_mm: float = 8.0) -> TetMesh:
    """The half ellipsoid of :func:`hemi_ellipsoid_mesh` with a smooth (faceted) surface, meshed
    by TetGen with quality tets of about ``edge_mm``: meant for convergence studies, where the
    stair-stepped boundary of the voxel-like mesh would change with the spacing. Point data as in
    :func:`hemi_ellipsoid_mesh`."""
    import tetgen  # imported here: the solver runs on machines without TetGen

    radii = np.asarray(radii_mm, float)
    points, triangles = _half_ball_surface(edge_mm / radii.mean())
    points = points * radii[[0, 1, 2]]
    generator = tetgen.TetGen(points, triangles)
    nodes, tets, *_ = generator.tetrahedralize(minratio=1.5, mindihedral=12.0, nobisect=True,
                                               maxvolume=edge_mm**3 / (6 * np.sqrt(2)))
    return _with_breast_node_sets(TetMesh(nodes, tets), radii)


def project_to_hemi_ellipsoid(points: np.ndarray, radii_mm) -> np.ndarray:
    """Move boundary points (K, 3) mm onto the half ellipsoid's surface: points on the chest plane
    y = 0 stay in it (pulled onto the rim where they lie outside), others go radially (in the
    coordinates scaled by the radii) onto the dome."""
    radii = np.asarray(radii_mm, float)
    scaled = points / radii
    norm = np.linalg.norm(scaled, axis=1)
    on_chest = np.abs(points[:, 1]) < 1e-6 * radii.max()
    factor = np.where(on_chest, np.minimum(1.0, 1.0 / np.maximum(norm, 1e-12)), 1.0 / np.maximum(norm, 1e-12))
    return scaled * factor[:, None] * radii


def refined_hemi_ellipsoid_mesh(radii_mm=(80.0, 70.0, 75.0), edge_mm: float = 16.0, levels: int = 1) -> TetMesh:
    """:func:`smooth_hemi_ellipsoid_mesh` refined ``levels`` times by splitting each tet into eight,
    new surface nodes projected onto the ellipsoid: a nested family for convergence studies
    (edges of about edge_mm / 2^levels)."""
    mesh = smooth_hemi_ellipsoid_mesh(radii_mm, edge_mm)
    for _ in range(levels):
        mesh = refine_uniform(mesh, lambda p: project_to_hemi_ellipsoid(p, radii_mm))
    return _with_breast_node_sets(mesh, np.asarray(radii_mm, float))


def _with_breast_node_sets(mesh: TetMesh, radii: np.ndarray) -> TetMesh:
    """Positively oriented tets and point data ``chest_wall`` (y = 0) and ``surface`` (the other
    boundary nodes)."""
    tets = mesh.tets.copy()
    negative = mesh.volumes < 0
    tets[negative] = tets[negative][:, [0, 2, 1, 3]]
    boundary = boundary_nodes(tets, len(mesh.nodes))
    chest = np.abs(mesh.nodes[:, 1]) < 1e-6 * radii.max()
    return TetMesh(mesh.nodes, tets, point_data={"chest_wall": chest.astype(np.uint8),
                                                 "surface": (boundary & ~chest).astype(np.uint8)})
