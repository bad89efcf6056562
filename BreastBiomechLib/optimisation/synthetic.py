"""A synthetic fitting problem whose truth lies inside the fitted family, for tests and
benchmarks: a stair-stepped half-ellipsoid breast (no TetGen, no VTK) with a glandular core, an
optional tumour and pectoral muscle layer, a textured MR-like image, and a "measured" image that
is the FE prediction at known truth parameters under a 25 % LR plate compression.

LPS millimetres, chest wall on y = 0, the breast anterior (y < 0); moduli in Pa.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
from scipy.ndimage import gaussian_filter

from BreastBiomechLib import labels
from BreastBiomechLib.io.cases import case_from_dict, compression_case
from BreastBiomechLib.mesh.primitives import hemi_ellipsoid_mesh
from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.solver.placement import final_planes

INTENSITY = {"fat": 1000.0, "glandular": 420.0, "muscle": 330.0, "tumour": 250.0}


@dataclass
class SyntheticCase:
    """``mesh`` (cell array ``tissue``; node sets ``chest_wall``, ``skin``, ``breast_skin``,
    ``fov_cut``), the ``undeformed`` image, the final plate ``planes`` (as plates.json holds them)."""

    mesh: TetMesh
    undeformed: sitk.Image
    planes: list[dict]


def synthetic_case(radii_mm=(40.0, 35.0, 40.0), element_mm: float = 6.0, voxel_mm=(2.0, 2.0, 2.0),
                   muscle_mm: float = 0.0, tumour_mm: float = 0.0, compression: float = 0.25,
                   seed: int = 3, pull_corners: bool = False) -> SyntheticCase:
    """The breast of ``radii_mm`` (LR, AP depth, SI) meshed by cubes of ``element_mm``, its
    posterior ``muscle_mm`` of pectoral muscle under the central base (0: none), a central glandular core (half the radii) and a
    tumour of diameter ``tumour_mm`` inside it (0: none); the image at ``voxel_mm`` with a smooth
    random texture (``seed``) so that interior motion shows; plates closing by ``compression``;
    ``pull_corners``: the stairs' protruding corners moved onto the ellipsoid (see
    :func:`~BreastBiomechLib.mesh.primitives.hemi_ellipsoid_mesh`)."""
    a, d, b = (float(r) for r in radii_mm)
    mesh = hemi_ellipsoid_mesh((a, d, b), spacing_mm=element_mm, pull_corners=pull_corners)
    core_centre = np.array([0.0, -0.4 * d, 0.0])
    core_radii = np.array([0.55 * a, 0.4 * d, 0.55 * b])
    tumour_centre = core_centre + [0.15 * a, 0.0, 0.0]

    def tissue_at(points):
        tissue = np.full(len(points), labels.FAT.label)
        tissue[(((points - core_centre) / core_radii) ** 2).sum(axis=1) <= 1.0] = labels.GLANDULAR.label
        if tumour_mm > 0:
            tissue[np.linalg.norm(points - tumour_centre, axis=1) <= tumour_mm / 2] = labels.TUMOUR.label
        if muscle_mm > 0:  # under the central base, clear of the plates' rounded edges at the sides
            central = (points[:, 0] / (0.7 * a)) ** 2 + (points[:, 2] / (0.7 * b)) ** 2 <= 1.0
            tissue[(points[:, 1] > -muscle_mm) & central] = labels.MUSCLE.label
        return tissue

    mesh.cell_data["tissue"] = tissue_at(mesh.nodes[mesh.tets].mean(axis=1)).astype(np.uint8)
    surface = mesh.point_data["surface"].astype(bool)
    breast_skin = surface & (mesh.nodes[:, 1] < 0.0)
    mesh.point_data.update({"skin": surface.astype(np.uint8), "breast_skin": breast_skin.astype(np.uint8),
                            "fov_cut": np.zeros(len(mesh.nodes), np.uint8)})

    spacing = np.asarray(voxel_mm, float)
    low = np.array([-1.45 * a, -1.7 * d, -1.45 * b])  # room for the compressed breast's bulge
    high = np.array([1.45 * a, 0.3 * d, 1.45 * b])
    size = np.ceil((high - low) / spacing).astype(int) + 1
    k, j, i = np.meshgrid(*(np.arange(n) for n in size[::-1]), indexing="ij")
    points = np.stack([low[0] + spacing[0] * i, low[1] + spacing[1] * j, low[2] + spacing[2] * k], axis=-1)
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    body = ((x / a) ** 2 + (y / d) ** 2 + (z / b) ** 2 <= 1.0) & (y <= 0)
    tissue = tissue_at(points.reshape(-1, 3)).reshape(body.shape)
    base = np.zeros(body.shape)
    for name, value in INTENSITY.items():
        base[tissue == labels.tissue(name).label] = value
    texture = gaussian_filter(np.random.default_rng(seed).standard_normal(body.shape), 1.5)
    values = np.where(body, base * (1.0 + 0.6 * texture), 0.0).astype(np.float32)
    image = sitk.GetImageFromArray(values)
    image.SetOrigin(tuple(float(v) for v in low))
    image.SetSpacing(tuple(float(v) for v in spacing))

    model, _ = case_from_dict(compression_case(mesh, "synthetic.vtu", "LR", compression), mesh)
    return SyntheticCase(mesh, image, final_planes(model.loading.plates))


def measured_at(case: SyntheticCase, space, truth: dict[str, float], relaxation=None, device=None) -> sitk.Image:
    """The "measured" compressed image of ``case``: the prediction at the ``truth`` values of
    ``space``'s free parameters. Raises RuntimeError if the truth does not solve."""
    from BreastBiomechLib.optimisation.forward import FittingProblem

    problem = FittingProblem(space, case.mesh, case.undeformed, case.undeformed, case.planes,
                             relaxation=relaxation, device=device)
    solution = problem.solve(space.unit(truth))[0]
    if not solution.ok:
        raise RuntimeError(f"the synthetic truth does not solve: {solution.message}")
    return problem.predict(solution.displacement).image
