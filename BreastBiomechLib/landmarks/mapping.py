"""Landmarks through an FE displacement, and their errors (seed section 3.2, Table 2).

A reference landmark is located in its reference tet (barycentric coordinates) and moves with
the tet's nodes: exact for any displacement that is linear over each tet, affine maps included.
Positions in LPS millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from BreastBiomechLib.landmarks.points import Landmarks
from BreastBiomechLib.mesh.distance import point_triangle_distance
from BreastBiomechLib.mesh.tetmesh import TetMesh, boundary_faces

_CANDIDATES = 32  # tets searched for the nearest one to a point outside the mesh
_NEAREST = 64  # tets, by their centroids' distance, tried first for holding a point
_BLOCK = 4096  # points tried at a time


@dataclass
class PointLocation:
    """``tets`` (K,): the tet holding each point; ``weights`` (K, 4): its barycentric
    coordinates there; ``outside_mm`` (K,): how far outside the mesh a point lies (0 inside;
    such points follow their nearest tet's map, linearly extrapolated)."""

    tets: np.ndarray
    weights: np.ndarray
    outside_mm: np.ndarray


def locate_points(mesh: TetMesh, points: np.ndarray) -> PointLocation:
    """The reference tet and barycentric coordinates of each point (K, 3) LPS mm; a point
    outside the mesh takes the nearest tet (searched among those with the nearest centroids).

    Each point is first tried in the :data:`_NEAREST` tets with the nearest centroids, all points
    at once (a node of the mesh, shared by some twenty tets, has them all there); only a point
    that none of them holds is tried against every tet. Where several tets hold a point (on a
    shared face, edge or node) the one it lies deepest in is taken, the lowest numbered on a tie."""
    from scipy.spatial import cKDTree  # SciPy on first use: the command line's parsers import this module

    points = np.atleast_2d(np.asarray(points, dtype=float))
    corners = mesh.nodes[mesh.tets]                                   # (M, 4, 3)
    edges = np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1))  # columns p1-p0, p2-p0, p3-p0
    to_barycentric = np.linalg.inv(edges)
    centroids = corners.mean(axis=1)
    tets = np.full(len(points), -1, dtype=np.int64)
    weights = np.empty((len(points), 4))
    outside = np.zeros(len(points))
    if len(points):
        nearest = cKDTree(centroids).query(points, k=min(_NEAREST, len(centroids)))[1].reshape(len(points), -1)
        nearest.sort(axis=1)  # a tie goes to the lowest numbered tet, as a search over all of them gives it
        for start in range(0, len(points), _BLOCK):
            block = slice(start, start + _BLOCK)
            near = nearest[block]
            b = np.einsum("kcij,kcj->kci", to_barycentric[near], points[block, None] - corners[near, 0])
            full = np.concatenate([1.0 - b.sum(axis=2, keepdims=True), b], axis=2)  # (k, c, 4)
            least = full.min(axis=2)
            best = least.argmax(axis=1)
            rows = np.arange(len(near))
            held = least[rows, best] >= -1e-9
            tets[block][held] = near[rows, best][held]
            weights[block][held] = full[rows, best][held]
    for k in np.flatnonzero(tets < 0):  # held by none of its nearest tets: all of them, then outside
        p = points[k]
        b = np.einsum("mij,mj->mi", to_barycentric, p - corners[:, 0])
        full = np.column_stack([1.0 - b.sum(axis=1), b])
        least = full.min(axis=1)
        best = int(np.argmax(least))
        if least[best] < -1e-9:  # outside: the nearest of the tets with the nearest centroids
            candidates = np.argsort(np.linalg.norm(centroids - p, axis=1))[:_CANDIDATES]
            distances = [_distance_to_tet(p, corners[c]) for c in candidates]
            best = int(candidates[int(np.argmin(distances))])
            outside[k] = float(min(distances))
        tets[k], weights[k] = best, full[best]
    return PointLocation(tets, weights, outside)


def _distance_to_tet(p: np.ndarray, corners: np.ndarray) -> float:
    """Distance from p to the closest point of the tet's faces (p outside it)."""
    faces = corners[[(0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)]]
    return float(point_triangle_distance(np.tile(p, (4, 1)), faces[:, 0], faces[:, 1], faces[:, 2]).min())


def outside_tolerance_mm(mesh: TetMesh) -> float:
    """How far outside ``mesh`` a landmark may lie and still be mapped (mm): 5 mm, or three
    quarters of the mean edge of the mesh's surface triangles where that is larger. A skin
    landmark at a sharp feature lies up to about half an edge outside a coarse mesh's faceted
    surface (the nipple of the 450 cm3 test phantom 6.1 mm outside a 10 mm mesh)."""
    faces = boundary_faces(mesh.tets)[0]
    if len(faces) == 0:
        return 5.0
    corners = mesh.nodes[faces]
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)
    return max(5.0, 0.75 * float(edges.mean()))


class LandmarkMapper:
    """Moves one set of reference ``landmarks`` with nodal displacements of one ``mesh``: each
    landmark is located in its reference tet once, so mapping many displacements (an
    optimisation's evaluations) costs a weighted sum each. Landmarks more than
    ``max_outside_mm`` outside the mesh (None: :func:`outside_tolerance_mm`) are refused: their
    motion would be a guess (skin fiducials just outside a smoothed surface are within it)."""

    def __init__(self, mesh: TetMesh, landmarks: Landmarks, max_outside_mm: float | None = None):
        if max_outside_mm is None:
            max_outside_mm = outside_tolerance_mm(mesh)
        where = locate_points(mesh, landmarks.positions)
        far = where.outside_mm > max_outside_mm
        if far.any():
            names = [f"{landmarks.labels[i]} ({where.outside_mm[i]:.1f} mm)" for i in np.flatnonzero(far)]
            raise ValueError(f"landmarks outside the mesh by more than {max_outside_mm:.3g} mm: {', '.join(names)}; "
                             "are they in the mesh's frame (LPS mm)?")
        self.mesh = mesh
        self.landmarks = landmarks
        self._nodes = mesh.tets[where.tets]  # (K, 4) the nodes of each landmark's tet
        self._weights = where.weights

    def map(self, displacement_mm: np.ndarray) -> Landmarks:
        """The landmarks moved by the nodal displacements (N, 3) mm."""
        displacement = np.asarray(displacement_mm, dtype=float)
        if displacement.shape != self.mesh.nodes.shape:
            raise ValueError(f"displacements must be one 3-vector per node, shape {self.mesh.nodes.shape}; "
                             f"got {displacement.shape}")
        moved = self.landmarks.positions + np.einsum("ki,kij->kj", self._weights, displacement[self._nodes])
        return Landmarks(moved, list(self.landmarks.labels), list(self.landmarks.descriptions))


def map_landmarks(mesh: TetMesh, displacement_mm: np.ndarray, landmarks: Landmarks,
                  max_outside_mm: float | None = None) -> Landmarks:
    """``landmarks`` (reference, LPS mm) moved by the nodal displacements (N, 3) mm of ``mesh``
    (see :class:`LandmarkMapper`, which also refuses landmarks far outside the mesh)."""
    displacement = np.asarray(displacement_mm, dtype=float)
    if displacement.shape != mesh.nodes.shape:
        raise ValueError(f"displacements must be one 3-vector per node, shape {mesh.nodes.shape}; "
                         f"got {displacement.shape}")
    return LandmarkMapper(mesh, landmarks, max_outside_mm).map(displacement)


@dataclass
class LandmarkErrors:
    """Per landmark (matched by label): ``displacement_mm``, how far it moved in the measurement
    (|measured - reference|), and ``error_mm``, how far the prediction misses it (|predicted -
    measured|)."""

    labels: list[str]
    displacement_mm: np.ndarray
    error_mm: np.ndarray

    def summary(self) -> dict:
        """mean, sd (population) and max of both, in mm, as the seed's Table 2 reports them."""
        def stats(v):
            return {"mean": float(v.mean()), "sd": float(v.std()), "max": float(v.max())}
        return {"landmarks": len(self.labels), "displacement_mm": stats(self.displacement_mm),
                "error_mm": stats(self.error_mm)}


def landmark_errors(reference: Landmarks, predicted: Landmarks, measured: Landmarks) -> LandmarkErrors:
    """Errors of ``predicted`` against ``measured`` landmarks, matched by label (those in all
    three sets); a clear error when none match."""
    common = [label for label in measured.labels if label in predicted.labels and label in reference.labels]
    if not common:
        raise ValueError("the reference, predicted and measured landmarks share no label; landmarks are "
                         "matched by label (e.g. L01, F1, nipple)")
    r = np.array([reference.position(label) for label in common])
    p = np.array([predicted.position(label) for label in common])
    m = np.array([measured.position(label) for label in common])
    return LandmarkErrors(common, np.linalg.norm(m - r, axis=1), np.linalg.norm(p - m, axis=1))
