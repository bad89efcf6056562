"""Tetrahedral meshes (LPS) <-> MRML model nodes holding a vtkUnstructuredGrid (RAS)."""

from __future__ import annotations

from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.mrml import frames

_VECTOR_HINT = "vectors in LPS"  # point/cell arrays with 3 components are flipped with the points


def _flip_mesh(mesh: TetMesh, vector_arrays: tuple[str, ...]) -> TetMesh:
    def convert(data):
        return {k: (frames.flip(v) if k in vector_arrays else v) for k, v in data.items()}

    # diag(-1, -1, 1) is a rotation (det +1): tet orientation is kept
    return TetMesh(frames.flip(mesh.nodes), mesh.tets, convert(mesh.point_data), convert(mesh.cell_data))


def tetmesh_to_model_node(mesh: TetMesh, scene, name: str = "Mesh", node=None,
                          vector_arrays: tuple[str, ...] = ("displacement", "fibre_direction")):
    """Put ``mesh`` into a (new or given) model node as an unstructured grid in RAS.

    Arrays named in ``vector_arrays`` (3 components, LPS) are flipped to RAS with the points, so a
    displacement shown in Slicer points the right way; other arrays are copied as they are."""
    if node is None:
        node = scene.AddNewNodeByClass("vtkMRMLModelNode", name)
        node.CreateDefaultDisplayNodes()
    node.SetAndObserveMesh(_flip_mesh(mesh, vector_arrays).to_vtk())
    return node


def tetmesh_from_model_node(node, vector_arrays: tuple[str, ...] = ("displacement", "fibre_direction")) -> TetMesh:
    """The model node's unstructured grid as a TetMesh in LPS (inverse of tetmesh_to_model_node)."""
    if node is None or node.GetMeshType() != node.UnstructuredGridMeshType or node.GetUnstructuredGrid() is None:
        raise ValueError("the model node holds no volumetric (unstructured grid) mesh; "
                         "make one with the BreastMesh module or load a .vtu file")
    return _flip_mesh(TetMesh.from_vtk(node.GetUnstructuredGrid()), vector_arrays)
