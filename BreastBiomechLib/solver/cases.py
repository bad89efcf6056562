"""Reference models for verification and benchmarks: plate compression of a hemi-ellipsoidal
breast on a chest wall (the seed's set-up: medio-lateral plates, chest wall fixed
anterior-posteriorly, one node fixed against rigid motion)."""

from __future__ import annotations

import numpy as np

from BreastBiomechLib.mesh.primitives import hemi_ellipsoid_mesh, smooth_hemi_ellipsoid_mesh
from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.solver.materials import ElementMaterials, Material
from BreastBiomechLib.solver.model import Loading, Model
from BreastBiomechLib.solver.placement import compression_plates
from BreastBiomechLib.solver.supports import support_constraints


def hemi_ellipsoid_compression(spacing_mm: float = 5.0, compression: float = 0.25,
                               material: Material | None = None, radii_mm=(80.0, 70.0, 75.0),
                               total_time: float = 1.0, settle_time: float = 0.25,
                               damping: float = 30.0, formulation: str = "T4ANP", smooth: bool = False) -> Model:
    """Two plates tangent to the breast at its medial and lateral extremes (x) close by
    ``compression`` x the breast's width (half each). The chest wall as in the seed, its nodes
    (y = 0) fixed in y, with the anchor patches of :func:`~BreastBiomechLib.solver.supports.
    support_constraints` against rigid motion. ``smooth`` meshes the smooth surface with TetGen
    (edges of about ``spacing_mm``) instead of the stair-stepped Kuhn grid. Default tissue: the
    seed's solver check (E = 10 kPa, nu = 0.49, 1000 kg/m^3)."""
    mesh = smooth_hemi_ellipsoid_mesh(radii_mm, spacing_mm) if smooth else hemi_ellipsoid_mesh(radii_mm, spacing_mm)
    return plate_compression(mesh, compression, material, total_time, settle_time, damping, formulation)


def plate_compression(mesh: TetMesh, compression: float = 0.25, material: Material | None = None,
                      total_time: float = 1.0, settle_time: float = 0.25, damping: float = 30.0,
                      formulation: str = "T4ANP") -> Model:
    """The loading of :func:`hemi_ellipsoid_compression` on a given ``mesh`` with point data
    ``chest_wall`` and ``surface`` (as the meshes of :mod:`BreastBiomechLib.mesh.primitives` have)."""
    material = material or Material(E=10e3, nu=0.49)
    chest = np.flatnonzero(mesh.point_data["chest_wall"])
    surface = np.flatnonzero(mesh.point_data["surface"])
    plates = compression_plates(mesh, "LR", compression, surface, names=("medial", "lateral"))
    constraints = support_constraints(mesh.nodes, chest, (False, True, False))
    loading = Loading(constraints, plates, total_time=total_time, settle_time=settle_time)
    return Model(mesh, ElementMaterials.uniform(len(mesh.tets), material), loading,
                 formulation=formulation, damping=damping)
