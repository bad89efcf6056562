"""The order in which the solver numbers a mesh's nodes and elements on the CPU.

The step's element kernels gather each element's four node displacements and scatter its four
nodal forces, one corner at a time. Where elements that follow one another in memory are
neighbours in space and their nodes neighbours in memory, those reads and adds stay in a few
cache lines; where the numbering is scattered, as TetGen leaves it, nearly every one is a line of
its own. On the CPU ``solve_batch`` therefore numbers a scattered mesh's nodes and elements along a
Z-order (Morton) curve through the mesh for the solve and gives every result back in the mesh's
own numbering: the model solved is the same, its results differ in float32 round-off only (the
order of the force sums). Measured on the 2-core developer machine (docs/benchmarks.md,
2026-11-28), one model relaxed to rest in TetGen's numbering and renumbered: a 37k-tet breast
5 % faster, a 139k-tet one 8 %.

Not on CUDA: there a single relaxation of the 139k-tet breast steps 12-13 % faster renumbered
(0.021 s of 0.168 s on an H100), less than the host time the renumbering takes per solve
(0.16-0.26 s on that machine's host: the codes, the permuted model and materials), and batches of four or more models gain
nothing, sixteen are 2-3 % slower (a batch's models are innermost, so a warp's threads share each
element's reads already).

A mesh whose own order is local already is kept: the structured (Kuhn) grids of
:mod:`BreastBiomechLib.mesh.primitives` number consecutive elements as the same tet of adjacent
cubes, so consecutive reads of a corner are consecutive nodes, which no space-filling curve
matches (the Z-order numbering of the benchmark's 160k-tet grid made its relaxation 1.6 times
slower on an H100). The rule: renumber where the mesh's own order touches more than
:data:`SCATTERED_SECTORS` 32-byte sectors per read of one corner by 32 consecutive elements (a
Kuhn grid 13, TetGen's order 28-31, the Z-order 10-12), the mesh has at least
:data:`MIN_ELEMENTS` elements and the batch at most :data:`MAX_BATCH` models.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.solver.materials import ElementMaterials
from BreastBiomechLib.solver.model import Model, Plate

SCATTERED_SECTORS = 20.0  # renumber where a corner read touches more sectors (Kuhn grid 13, TetGen 29, Z-order 10-12)
MIN_ELEMENTS = 20_000  # smaller meshes are solved in their own order (their state stays in cache)
MAX_BATCH = 2  # larger batches are solved in the mesh's order (a batch's models share each element's reads)
WARP = 32  # consecutive elements whose reads of one corner are counted together (a GPU warp)
SECTOR_BYTES = 32  # the unit a GPU reads memory in
VEC3_BYTES = 12  # one node's displacement or force (float32)
_MORTON_BITS = 10  # per axis: a 1024^3 grid over the mesh's bounding box


def morton_codes(points: np.ndarray) -> np.ndarray:
    """(K,) Z-order codes of points (K, 3) in their bounding box: the bits of the three
    quantised coordinates interleaved, so that sorting by code walks the box octant by octant."""
    points = np.asarray(points, float)
    low, high = points.min(axis=0), points.max(axis=0)
    cells = (1 << _MORTON_BITS) - 1
    q = ((points - low) / np.maximum(high - low, 1e-300) * cells).astype(np.uint64)
    code = np.zeros(len(points), np.uint64)
    for bit in range(_MORTON_BITS):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return code


def sectors_per_corner_read(tets: np.ndarray) -> float:
    """The mean number of 32-byte sectors that one warp's read of one corner's node displacement
    touches when the elements ``tets`` (M, 4) are taken 32 at a time in their order (12 to 13 for a
    Kuhn grid, up to 32 for a scattered numbering)."""
    full = len(tets) // WARP * WARP
    if full == 0:
        return 0.0
    sectors = np.sort((tets[:full].astype(np.int64) * VEC3_BYTES // SECTOR_BYTES).reshape(-1, WARP, 4), axis=1)
    return float(np.mean(1 + np.count_nonzero(np.diff(sectors, axis=1), axis=1)))


@dataclass(frozen=True)
class SolverOrder:
    """A renumbering of a mesh for the solve: the solver's node i is the mesh's node ``nodes[i]``
    and its element e the mesh's element ``elements[e]``."""

    nodes: np.ndarray
    elements: np.ndarray

    @classmethod
    def for_mesh(cls, mesh: TetMesh, n_models: int = 1) -> "SolverOrder | None":
        """The Z-order renumbering of ``mesh`` for a batch of ``n_models`` where the rule of this
        module asks for one, else None."""
        if (n_models > MAX_BATCH or len(mesh.tets) < MIN_ELEMENTS
                or sectors_per_corner_read(mesh.tets) <= SCATTERED_SECTORS):
            return None
        return cls(np.argsort(morton_codes(mesh.nodes), kind="stable"),
                   np.argsort(morton_codes(mesh.nodes[mesh.tets].mean(axis=1)), kind="stable"))

    @cached_property
    def rank(self) -> np.ndarray:
        """(N,) the solver's number of each of the mesh's nodes."""
        rank = np.empty(len(self.nodes), np.int64)
        rank[self.nodes] = np.arange(len(self.nodes))
        return rank

    def tets(self, tets: np.ndarray) -> np.ndarray:
        """The connectivity (M, 4) in the solver's numbering (each element's corners in their order)."""
        return self.rank[tets][self.elements].astype(tets.dtype)

    def node_values(self, values: np.ndarray | None) -> np.ndarray | None:
        """Per-node values (N, ...) of the mesh in the solver's order (None, or values of another
        length - which the solver refuses with its own message - pass through)."""
        if values is None or np.shape(values)[:1] != (len(self.nodes),):
            return values
        return np.asarray(values)[self.nodes]

    def mesh_values(self, values: np.ndarray) -> np.ndarray:
        """Per-node values (N, ...) in the solver's order back in the mesh's."""
        return np.asarray(values)[self.rank]

    def materials(self, materials: ElementMaterials) -> ElementMaterials:
        """Per-element materials in the solver's order (a set of another length passes through)."""
        if len(materials.mu) != len(self.elements):
            return materials
        e = self.elements
        return replace(materials, mu=materials.mu[e], kappa=materials.kappa[e], eta=materials.eta[e],
                       fibre=materials.fibre[e], density=materials.density[e], prony_g=materials.prony_g[e],
                       prony_tau=materials.prony_tau[e])

    def plates(self, plates: list[Plate]) -> list[Plate]:
        """Plates with their contact nodes in the solver's numbering (a plate naming nodes outside
        the mesh passes through, for the solver to refuse)."""
        rank = self.rank
        return [replace(p, slave_nodes=rank[p.slave_nodes])
                if np.all((p.slave_nodes >= 0) & (p.slave_nodes < len(rank))) else p for p in plates]

    def model(self, model: Model) -> Model:
        """``model`` with its mesh, materials, constraints, supports, plates and pre-stressed state
        in the solver's numbering."""
        mesh, rank = model.mesh, self.rank
        renumbered = TetMesh(mesh.nodes[self.nodes], self.tets(mesh.tets),
                             point_data={k: np.asarray(v)[self.nodes] for k, v in mesh.point_data.items()},
                             cell_data={k: np.asarray(v)[self.elements] for k, v in mesh.cell_data.items()})
        loading = model.loading
        loading = replace(loading, constraints=[replace(c, nodes=rank[c.nodes]) for c in loading.constraints],
                          plates=self.plates(loading.plates),
                          supports=[replace(s, nodes=rank[s.nodes]) for s in loading.supports])
        prestate = None if model.prestate is None else replace(
            model.prestate, displacement=self.node_values(model.prestate.displacement))
        return replace(model, mesh=renumbered, materials=self.materials(model.materials), loading=loading,
                       prestate=prestate)
