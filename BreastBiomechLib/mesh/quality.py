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

from BreastBiomechLib.mesh.tetmesh import OUTWARD_FACES, TetMesh, cross

CRITERIA = {  # the failure criteria of QualityReport.failing, in words
    "shape_factor": "shape factor < 0.001",
    "face_angle": "face corner angle < 5 or > 150 deg",
    "aspect_ratio": "aspect ratio (longest / shortest edge) > 10",
    "any": "any of the three",
}
_EDGES = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])
DIHEDRAL_BINS = np.arange(0.0, 181.0, 5.0)
CHUNK = 20_000  # elements measured at a time
# the element's twelve face corners: at node _CORNER_AT, between the edges to the face's next and
# previous nodes (faces as OUTWARD_FACES), and the two faces meeting at each edge of _EDGES
_CORNER_AT = OUTWARD_FACES.ravel()
_CORNER_NEXT = np.roll(OUTWARD_FACES, -1, axis=1).ravel()
_CORNER_PREVIOUS = np.roll(OUTWARD_FACES, -2, axis=1).ravel()
_DIHEDRAL_FACES = np.array([sorted(set(range(4)) - {i, j}) for i, j in _EDGES])


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


def _length(u: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("...i,...i->...", u, u))


def _angle(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    cos = np.einsum("...i,...i->...", u, v) / (_length(u) * _length(v))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def mesh_quality(mesh: TetMesh) -> QualityReport:
    """Quality measures of every element of ``mesh`` (nodes in mm; measures are scale-free),
    computed :data:`CHUNK` elements at a time (a block's temporaries stay in cache: four times
    faster on a mesh of 200k elements than all at once)."""
    if len(mesh.tets) == 0:
        raise ValueError("the mesh has no elements to check")
    blocks = [element_measures(mesh.nodes[mesh.tets[start:start + CHUNK]]) for start in range(0, len(mesh.tets), CHUNK)]
    return QualityReport(*(np.concatenate(arrays) for arrays in zip(*blocks)))


def element_measures(p: np.ndarray) -> tuple[np.ndarray, ...]:
    """Shape factor, smallest and largest face corner, aspect ratio, smallest and largest dihedral
    angle (degrees) of the elements with node coordinates ``p`` (M, 4, 3)."""
    a, b, c = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    bc = cross(b, c)
    volume = np.einsum("ij,ij->i", a, bc) / 6.0
    numerator = (np.einsum("ij,ij->i", a, a)[:, None] * bc + np.einsum("ij,ij->i", b, b)[:, None]
                 * cross(c, a) + np.einsum("ij,ij->i", c, c)[:, None] * cross(a, b))
    with np.errstate(divide="ignore", invalid="ignore"):
        radius = _length(numerator) / (12.0 * np.abs(volume))
        optimal = 8.0 * radius**3 / (9.0 * np.sqrt(3.0))
        shape = np.where(np.isfinite(optimal) & (optimal > 0), np.abs(volume) / optimal, 0.0)

    # every face corner in one pass: corner k of face f at vertex f[k], between its two edges
    u = p[:, _CORNER_NEXT] - p[:, _CORNER_AT]
    v = p[:, _CORNER_PREVIOUS] - p[:, _CORNER_AT]
    corners = _angle(u, v)  # (M, 12)

    edges = _length(p[:, _EDGES[:, 1]] - p[:, _EDGES[:, 0]])
    with np.errstate(divide="ignore"):
        aspect = edges.max(axis=1) / edges.min(axis=1)

    f = p[:, OUTWARD_FACES]  # (M, 4, 3 nodes, 3)
    normals = cross(f[:, :, 1] - f[:, :, 0], f[:, :, 2] - f[:, :, 0])
    normals = normals * np.sign(volume)[:, None, None]  # outward for positively oriented tets
    # the faces at edge (i, j) are those opposite the other two vertices
    dihedral = 180.0 - _angle(normals[:, _DIHEDRAL_FACES[:, 0]], normals[:, _DIHEDRAL_FACES[:, 1]])  # (M, 6)
    return shape, corners.min(axis=1), corners.max(axis=1), aspect, dihedral.min(axis=1), dihedral.max(axis=1)
