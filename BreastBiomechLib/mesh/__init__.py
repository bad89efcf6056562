"""Tetrahedral meshes of the breast: the :class:`TetMesh` container and its VTK conversion."""

from BreastBiomechLib.mesh.tetmesh import TetMesh

__all__ = ["TetMesh"]
