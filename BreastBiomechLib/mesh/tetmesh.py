"""A four-node tetrahedral mesh with per-node and per-element data.

Nodes in millimetres, ITK physical space (LPS). Element connectivity is 0-based and positively
oriented (the signed volume of each tet is positive). Cell data ``tissue`` holds label values of
:mod:`BreastBiomechLib.labels`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from BreastBiomechLib.errors import InputError
from BreastBiomechLib.rows import unique_rows


def regular_tet_volume_mm3(edge_mm: float) -> float:
    """Volume (mm³) of the regular tetrahedron of edge ``edge_mm`` (mm): edge³ / (6 √2), the
    largest element TetGen is allowed at that edge."""
    return edge_mm**3 / (6.0 * np.sqrt(2.0))


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The cross product along the last axis of (..., 3) arrays: ``np.cross`` without its axis
    handling, the same numbers in half the time (the mesh repair's local checks call it on a few
    dozen elements at a time, tens of thousands of times)."""
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def signed_volumes(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes of the tets (M, 4) over ``nodes`` (N, 3), in the nodes' units cubed;
    positive where a tet's first three edges from its node 0 form a right-handed triple."""
    return signed_volumes_of(nodes[tets])


def signed_volumes_of(p: np.ndarray) -> np.ndarray:
    """:func:`signed_volumes` of tets given by their corners' coordinates ``p`` (M, 4, 3)."""
    return np.einsum("ij,ij->i", p[:, 1] - p[:, 0], cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])) / 6.0


OUTWARD_FACES = np.array([(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)])  # face k opposite vertex k, outward


def boundary_faces(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boundary faces (F, 3) (faces of one element only) and the element each belongs to (F,);
    for a positively oriented mesh the faces are ordered with outward normals."""
    faces = tets[:, OUTWARD_FACES].reshape(-1, 3)
    _, inverse, counts = unique_rows(np.sort(faces, axis=1), return_inverse=True, return_counts=True)
    single = counts[inverse] == 1
    return faces[single], np.repeat(np.arange(len(tets)), 4)[single]


def vtk_cells(connectivity: np.ndarray):
    """A vtkCellArray of cells with the same number of points, from (K, n) point ids."""
    import vtk
    from vtk.util import numpy_support as nps

    per_cell = connectivity.shape[1]
    cells = vtk.vtkCellArray()
    offsets = nps.numpy_to_vtk(np.arange(0, per_cell * len(connectivity) + 1, per_cell, dtype=np.int64), deep=True)
    ids = nps.numpy_to_vtk(np.ascontiguousarray(connectivity, dtype=np.int64).ravel(), deep=True,
                           array_type=vtk.VTK_ID_TYPE)
    cells.SetData(offsets, ids)
    return cells


def boundary_nodes(tets: np.ndarray, n_nodes: int) -> np.ndarray:
    """Boolean (N,): nodes on faces that belong to one tet only (the mesh boundary)."""
    mask = np.zeros(n_nodes, bool)
    mask[boundary_faces(tets)[0].ravel()] = True
    return mask


@dataclass
class TetMesh:
    """Nodes (N, 3) LPS mm, tets (M, 4) int64, and named point/cell arrays (first axis N or M)."""

    nodes: np.ndarray
    tets: np.ndarray
    point_data: dict[str, np.ndarray] = field(default_factory=dict)
    cell_data: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.nodes = np.ascontiguousarray(self.nodes, dtype=np.float64).reshape(-1, 3)
        self.tets = np.ascontiguousarray(self.tets, dtype=np.int64).reshape(-1, 4)
        if len(self.tets) and (self.tets.min() < 0 or self.tets.max() >= len(self.nodes)):
            raise ValueError(f"tet connectivity refers to nodes outside 0..{len(self.nodes) - 1}")
        for kind, data, n in (("point", self.point_data, len(self.nodes)), ("cell", self.cell_data, len(self.tets))):
            for name, values in data.items():
                values = np.asarray(values)
                if values.shape[0] != n:
                    raise ValueError(f"{kind} array {name!r} has {values.shape[0]} rows, the mesh has {n} {kind}s")
                data[name] = values

    @property
    def volumes(self) -> np.ndarray:
        """Signed element volumes (mm^3); positive for a valid mesh."""
        return signed_volumes(self.nodes, self.tets)

    def node_set(self, name: str) -> np.ndarray:
        """Ids of the nodes where point array ``name`` is non-zero (a node set, e.g. chest_wall)."""
        if name not in self.point_data:
            raise ValueError(f"the node set {name!r} is not a point array of the mesh; it has "
                             f"{sorted(self.point_data) or 'none'}")
        return np.flatnonzero(np.asarray(self.point_data[name]).reshape(len(self.nodes), -1).any(axis=1))

    def to_vtk(self):
        """The mesh as a vtkUnstructuredGrid (points in LPS mm), arrays copied."""
        import vtk  # imported here: the solver uses meshes on machines without VTK
        from vtk.util import numpy_support as nps

        grid = vtk.vtkUnstructuredGrid()
        points = vtk.vtkPoints()
        points.SetData(nps.numpy_to_vtk(self.nodes, deep=True))
        grid.SetPoints(points)
        grid.SetCells(vtk.VTK_TETRA, vtk_cells(self.tets))
        for data, target in ((self.point_data, grid.GetPointData()), (self.cell_data, grid.GetCellData())):
            for name, values in data.items():
                array = nps.numpy_to_vtk(np.ascontiguousarray(values), deep=True)
                array.SetName(name)
                target.AddArray(array)
        return grid

    @classmethod
    def from_vtk(cls, grid) -> "TetMesh":
        """Read a vtkUnstructuredGrid of tetrahedra (points taken as LPS mm)."""
        import vtk
        from vtk.util import numpy_support as nps

        n_cells = grid.GetNumberOfCells()
        if n_cells and not np.all(nps.vtk_to_numpy(grid.GetDistinctCellTypesArray()) == vtk.VTK_TETRA):
            raise ValueError("the unstructured grid holds cells other than linear tetrahedra")
        nodes = nps.vtk_to_numpy(grid.GetPoints().GetData()).astype(np.float64) if grid.GetPoints() else np.zeros((0, 3))
        conn = nps.vtk_to_numpy(grid.GetCells().GetConnectivityArray()).astype(np.int64).reshape(-1, 4)

        def arrays(data):
            return {data.GetArrayName(i): nps.vtk_to_numpy(data.GetArray(i)).copy()
                    for i in range(data.GetNumberOfArrays()) if data.GetArray(i) is not None}

        return cls(nodes, conn, arrays(grid.GetPointData()), arrays(grid.GetCellData()))


def check_mesh(mesh: TetMesh, where: str) -> None:
    """Refuse a mesh that cannot be simulated (:class:`~BreastBiomechLib.errors.InputError`,
    ``where`` naming its source): no elements, non-finite coordinates or point and cell data,
    inverted or flat elements, an element given twice, nodes in no element (they would have no
    mass)."""
    if len(mesh.tets) == 0:
        raise InputError(f"{where}: the mesh has no tetrahedra")
    bad = np.flatnonzero(~np.isfinite(mesh.nodes).all(axis=1))
    if len(bad):
        raise InputError(f"{where}: {len(bad)} node(s) have coordinates that are not finite (first: node "
                         f"{bad[0]}); fix or remove them")
    for kind, data in (("point", mesh.point_data), ("cell", mesh.cell_data)):
        for name, values in data.items():
            if np.issubdtype(values.dtype, np.number) and not np.isfinite(values).all():
                raise InputError(f"{where}: the {kind} array {name!r} holds values that are not finite")
    volumes = mesh.volumes
    bad = np.flatnonzero(~(volumes > 0))
    if len(bad):
        raise InputError(f"{where}: {len(bad)} of {len(volumes)} elements are inverted or flat (signed volume <= 0; "
                         f"first: element {bad[0]}, {volumes[bad[0]]:.3g} mm^3); re-mesh, or reorder each "
                         "element's nodes so its volume is positive")
    _, first, counts = unique_rows(np.sort(mesh.tets, axis=1), return_index=True, return_counts=True)
    if (counts > 1).any():
        raise InputError(f"{where}: {int((counts > 1).sum())} element(s) appear more than once (first: element "
                         f"{first[counts > 1].min()}); remove the duplicates")
    unused = np.setdiff1d(np.arange(len(mesh.nodes)), mesh.tets.ravel())
    if len(unused):
        raise InputError(f"{where}: {len(unused)} node(s) belong to no element (first: node {unused[0]}); a node "
                         "without an element has no mass: remove them")
