"""The reference geometry of a tetrahedral mesh as the TLED solver uses it: shape-function
derivatives, volumes, element altitudes and the lumping of element masses onto the nodes.

A fit solves one mesh hundreds of times with other materials: :meth:`MeshGeometry.of` computes a
mesh's geometry once and hands the same object to every later solve of a mesh with the same
node coordinates and connectivity (compared by a digest of their bytes, so a mesh edited in place
is computed afresh). On ``bench optimise``'s 54k-tet mesh that is about 40 ms of host time per
batch the solves no longer spend (docs/benchmarks.md).

Units: node coordinates in metres (the solver's SI), derivatives in 1/m, volumes in m^3,
altitudes in m; frames as the mesh's (LPS axes).
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

KEPT_MESHES = 4  # geometries kept for later solves (a fit and its truth's mesh, a study's few meshes)
KEPT_BYTES = 512 * 2**20  # ... and no more host memory than this held by them (the newest is always kept)


def shape_derivatives(nodes_m: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reference dN_a/dX (M, 4, 3) in 1/m and volumes (M,) in m^3 of linear tets.

    With the edges e_i = X_i - X_0 (i = 1, 2, 3) as the columns of the Jacobian J, dN_i/dX is
    row i - 1 of J^-1, i.e. (e_j x e_k) / det J for (i, j, k) cyclic, and dN_0/dX minus their sum
    (written out rather than batched 3x3 inverses: several times faster on a solve's set-up)."""
    x = nodes_m[tets]
    e1, e2, e3 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
    c23, c31, c12 = np.cross(e2, e3), np.cross(e3, e1), np.cross(e1, e2)
    det = np.einsum("ij,ij->i", e1, c23)
    dhdx = np.empty((len(tets), 4, 3))
    dhdx[:, 1], dhdx[:, 2], dhdx[:, 3] = c23 / det[:, None], c31 / det[:, None], c12 / det[:, None]
    dhdx[:, 0] = -(dhdx[:, 1] + dhdx[:, 2] + dhdx[:, 3])
    return dhdx, det / 6.0


def characteristic_lengths(nodes_m: np.ndarray, tets: np.ndarray, vol: np.ndarray) -> np.ndarray:
    """Smallest altitude of each tet, 3 V / (largest face area) (m)."""
    x = nodes_m[tets]
    faces = [(1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2)]
    areas = np.stack([0.5 * np.linalg.norm(np.cross(x[:, b] - x[:, a], x[:, c] - x[:, a]), axis=1)
                      for a, b, c in faces], axis=1)
    return 3.0 * vol / areas.max(axis=1)


@dataclass(frozen=True)
class MeshGeometry:
    """One mesh's reference geometry: ``nodes_m`` (N, 3) m, ``tets`` (M, 4) int32, ``dhdx``
    (M, 4, 3) 1/m, ``vol`` (M,) m^3, ``length`` (M,) m (smallest altitudes) and ``lumping``, the
    (N, M) sparse matrix that gives each node a quarter of each of its elements' values. Shared
    between solves: its arrays are read-only (leave the matrix as it is too)."""

    nodes_m: np.ndarray
    tets: np.ndarray
    dhdx: np.ndarray
    vol: np.ndarray
    length: np.ndarray
    lumping: sp.csr_matrix

    _kept = OrderedDict()  # digest -> MeshGeometry, least recently used first
    _lock = threading.Lock()  # solves in threads (a Dask worker's) share the kept geometries

    @classmethod
    def of(cls, nodes_mm: np.ndarray, tets: np.ndarray) -> "MeshGeometry":
        """The geometry of the mesh of ``nodes_mm`` (N, 3) mm and ``tets`` (M, 4): computed on
        the first call for these coordinates and this connectivity, the same object after that
        (the last :data:`KEPT_MESHES` meshes are kept, up to :data:`KEPT_BYTES` of them)."""
        nodes_mm = np.ascontiguousarray(nodes_mm, np.float64)
        tets = np.ascontiguousarray(tets)
        digest = hashlib.blake2b(digest_size=16)
        for array in (nodes_mm, tets):
            digest.update(repr((array.dtype.str, array.shape)).encode())
            digest.update(array.data)
        key = digest.hexdigest()
        with cls._lock:
            geometry = cls._kept.get(key)
        if geometry is None:
            geometry = cls.compute(nodes_mm * 1e-3, tets)
        with cls._lock:
            cls._kept[key] = geometry
            cls._kept.move_to_end(key)
            while len(cls._kept) > 1 and (len(cls._kept) > KEPT_MESHES
                                          or sum(g.nbytes for g in cls._kept.values()) > KEPT_BYTES):
                cls._kept.popitem(last=False)
        return geometry

    @classmethod
    def compute(cls, nodes_m: np.ndarray, tets: np.ndarray) -> "MeshGeometry":
        """The geometry of nodes ``nodes_m`` (N, 3) m and ``tets`` (M, 4), computed now."""
        tets32 = np.asarray(tets).astype(np.int32)
        dhdx, vol = shape_derivatives(nodes_m, tets32)
        M, N = len(tets32), len(nodes_m)
        # columns sorted within each row: a node's sum runs over its elements in increasing order,
        # as np.bincount over tets.ravel() adds them (the same float64 sums, bit for bit)
        lumping = sp.csr_matrix((np.full(4 * M, 0.25), (tets32.ravel(), np.repeat(np.arange(M), 4))), shape=(N, M))
        lumping.sort_indices()
        geometry = cls(nodes_m, tets32, dhdx, vol, characteristic_lengths(nodes_m, tets32, vol), lumping)
        for array in (geometry.nodes_m, geometry.tets, geometry.dhdx, geometry.vol, geometry.length):
            array.flags.writeable = False
        return geometry

    @property
    def nbytes(self) -> int:
        """Host memory (bytes) its arrays hold."""
        return (sum(a.nbytes for a in (self.nodes_m, self.tets, self.dhdx, self.vol, self.length))
                + self.lumping.data.nbytes + self.lumping.indices.nbytes + self.lumping.indptr.nbytes)

    def lumped(self, per_volume: list[np.ndarray]) -> np.ndarray:
        """Nodal sums (N * B,) of B models, models innermost (node a of model b at a * B + b): a
        quarter of each element's value x its volume at each of its nodes, e.g. the lumped masses
        (kg) of element densities (kg/m^3)."""
        return np.asarray(self.lumping @ np.stack([np.asarray(v, np.float64) * self.vol for v in per_volume],
                                                  axis=1)).ravel()
