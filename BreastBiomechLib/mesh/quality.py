"""Element quality of a tetrahedral mesh, with the seed's ABAQUS/CAE failure criteria.

The seed (section 2.2.3) checks three criteria, an element failing any of them:
shape factor < 0.001 (element volume over that of the equilateral tet with the same
circumradius), a face corner angle < 5 or > 150 degrees, aspect ratio > 10 (longest over
shortest edge). The dihedral angles (between the faces meeting at an edge) are reported too:
they bound the explicit solver's stable time step, which slivers (dihedral angles near 0 or
180 degrees with fine face angles) shrink."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from BreastBiomechLib.mesh.tetmesh import OUTWARD_FACES, TetMesh

CRITERIA = {  # the failure criteria of QualityReport.failing, in words
    "shape_factor": "shape factor < 0.001",
    "face_angle": "face corner angle < 5 or > 150 deg",
    "aspect_ratio": "aspect ratio (longest / shortest edge) > 10",
    "any": "any of the three",
}
_EDGES = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])
DIHEDRAL_BINS = np.arange(0.0, 181.0, 5.0)


@dataclass
class QualityReport:
    """Per-element measures (arrays of length M) and the failing-element summary."""

    shape_factor: np.ndarray
    min_face_angle_deg: np.ndarray
    max_face_angle_deg: np.ndarray
    aspect_ratio: np.ndarray
    min_dihedral_deg: np.ndarray
    max_dihedral_deg: np.ndarray

    @property
    def elements(self) -> int:
        return len(self.shape_factor)

    def failing(self) -> dict[str, np.ndarray]:
        """Boolean masks of the elements failing each criterion, and ``any``."""
        masks = {
            "shape_factor": self.shape_factor < 1e-3,
            "face_angle": (self.min_face_angle_deg < 5.0) | (self.max_face_angle_deg > 150.0),
            "aspect_ratio": self.aspect_ratio > 10.0,
        }
        masks["any"] = masks["shape_factor"] | masks["face_angle"] | masks["aspect_ratio"]
        return masks

    def dihedral_histogram(self) -> tuple[np.ndarray, np.ndarray]:
        """Histograms of the per-element smallest and largest dihedral angle in the 5-degree bins
        of :data:`DIHEDRAL_BINS`: (counts of the minima, counts of the maxima)."""
        return (np.histogram(self.min_dihedral_deg, DIHEDRAL_BINS)[0],
                np.histogram(self.max_dihedral_deg, DIHEDRAL_BINS)[0])

    def summary(self) -> dict:
        """Counts and percentages of failing elements per criterion, and the extremes."""
        n = max(self.elements, 1)
        failing = self.failing()
        smallest, largest = self.dihedral_histogram()
        rows = {name: {"criterion": CRITERIA[name],
                       "count": int(mask.sum()), "percent": round(100.0 * mask.sum() / n, 4)}
                for name, mask in failing.items()}
        return {
            "elements": self.elements,
            "failing": rows,
            "shape_factor_min": float(self.shape_factor.min()),
            "face_angle_min_deg": float(self.min_face_angle_deg.min()),
            "face_angle_max_deg": float(self.max_face_angle_deg.max()),
            "aspect_ratio_max": float(self.aspect_ratio.max()),
            "dihedral_min_deg": float(self.min_dihedral_deg.min()),
            "dihedral_max_deg": float(self.max_dihedral_deg.max()),
            "dihedral_min_percentiles_deg": {p: float(np.percentile(self.min_dihedral_deg, p)) for p in (0.1, 1, 50)},
            "dihedral_histogram": {"bins_deg": DIHEDRAL_BINS.tolist(), "smallest_per_element": smallest.tolist(),
                                   "largest_per_element": largest.tolist()},
        }

    def cell_data(self) -> dict[str, np.ndarray]:
        """The per-element measures as mesh cell arrays (float32) plus ``quality_fails`` (uint8)."""
        arrays = {f"quality_{name}": getattr(self, name).astype(np.float32)
                  for name in ("shape_factor", "min_face_angle_deg", "max_face_angle_deg", "aspect_ratio",
                               "min_dihedral_deg", "max_dihedral_deg")}
        arrays["quality_fails"] = self.failing()["any"].astype(np.uint8)
        return arrays


def _angle(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    cos = np.einsum("...i,...i->...", u, v) / (np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def mesh_quality(mesh: TetMesh) -> QualityReport:
    """Quality measures of every element of ``mesh`` (nodes in mm; measures are scale-free)."""
    if len(mesh.tets) == 0:
        raise ValueError("the mesh has no elements to check")
    p = mesh.nodes[mesh.tets]  # (M, 4, 3)
    a, b, c = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    numerator = (np.einsum("ij,ij->i", a, a)[:, None] * np.cross(b, c) + np.einsum("ij,ij->i", b, b)[:, None]
                 * np.cross(c, a) + np.einsum("ij,ij->i", c, c)[:, None] * np.cross(a, b))
    with np.errstate(divide="ignore", invalid="ignore"):
        radius = np.linalg.norm(numerator, axis=1) / (12.0 * np.abs(volume))
        optimal = 8.0 * radius**3 / (9.0 * np.sqrt(3.0))
        shape = np.where(np.isfinite(optimal) & (optimal > 0), np.abs(volume) / optimal, 0.0)

    corners = []
    for face in OUTWARD_FACES:
        q = p[:, face]
        for k in range(3):
            corners.append(_angle(q[:, (k + 1) % 3] - q[:, k], q[:, (k + 2) % 3] - q[:, k]))
    corners = np.stack(corners, axis=1)

    edges = np.linalg.norm(p[:, _EDGES[:, 1]] - p[:, _EDGES[:, 0]], axis=2)
    with np.errstate(divide="ignore"):
        aspect = edges.max(axis=1) / edges.min(axis=1)

    normals = np.stack([np.cross(p[:, f[1]] - p[:, f[0]], p[:, f[2]] - p[:, f[0]]) for f in OUTWARD_FACES], axis=1)
    orientation = np.sign(volume)[:, None, None]  # outward for positively oriented tets
    normals = normals * orientation
    dihedral = []
    for i, j in _EDGES:  # the faces at edge (i, j) are those opposite the other two vertices
        k, l = sorted(set(range(4)) - {i, j})
        dihedral.append(180.0 - _angle(normals[:, k], normals[:, l]))
    dihedral = np.stack(dihedral, axis=1)
    return QualityReport(shape, corners.min(axis=1), corners.max(axis=1), aspect,
                         dihedral.min(axis=1), dihedral.max(axis=1))
