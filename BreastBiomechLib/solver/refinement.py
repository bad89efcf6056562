"""A model on the uniform refinement of its mesh (every tet split into eight, edges halved): the
same geometry, materials, loading and plates, with every node-based input carried to the new
midpoint nodes. Used to measure the discretisation error of a solution (the difference between
the solution on the mesh and on its refinement at the mesh's own nodes, which the refinement
keeps with their ids first).

A midpoint takes a node set (a constraint's nodes, a plate's contact nodes, a surface support's
nodes) where both ends of its edge are in the set and, where both ends lie on the boundary, the
edge does too (a chord through the volume between two surface nodes is not on the surface);
its prescribed values and reference-state displacement are the mean of the two ends'; its
constrained components those constrained at both ends. A plate's rounded edge is convex, so the
chord between two contact nodes clear of it (one on the flat face, one on the fillet) may pass
behind it: a midpoint that starts behind a plate is left out of that plate's contact nodes, as
the coarse mesh's face between those nodes is free there. Frames and units: LPS millimetres.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from BreastBiomechLib.mesh.refine import midpoint_edges, refine_uniform
from BreastBiomechLib.mesh.tetmesh import TetMesh, boundary_faces, boundary_nodes
from BreastBiomechLib.solver.materials import ElementMaterials
from BreastBiomechLib.solver.model import (PENETRATION_TOLERANCE_MM, Constraint, Model, Plate, ReferenceState,
                                           SurfaceSupport)
from BreastBiomechLib.solver.supports import surface_normals_and_areas

CHILDREN = 8  # tets per tet of a uniform refinement


class Refinement:
    """The uniform refinement of ``mesh`` and how its inputs map: ``refined`` (TetMesh, the
    coarse nodes first), ``edges`` (E, 2) each midpoint's coarse edge, ``surface_edge`` (E,)
    whether a midpoint may take a surface set (see the module)."""

    def __init__(self, mesh: TetMesh):
        self.coarse = mesh
        self.refined = refine_uniform(mesh)
        self.edges = midpoint_edges(mesh)
        on_boundary = boundary_nodes(mesh.tets, len(mesh.nodes))
        faces, _ = boundary_faces(mesh.tets)
        face_edges = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
        known = {tuple(e) for e in face_edges.tolist()}
        is_face_edge = np.array([tuple(e) in known for e in self.edges.tolist()], bool)
        both_on_boundary = on_boundary[self.edges].all(axis=1)
        self.surface_edge = is_face_edge | ~both_on_boundary

    def nodes_of(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The refined mesh's node ids of the set ``nodes`` (coarse ids: kept) with its midpoints,
        and for each midpoint the index of its edge in :attr:`edges`."""
        inside = np.zeros(len(self.coarse.nodes), bool)
        inside[np.asarray(nodes, np.int64)] = True
        edges = np.flatnonzero(inside[self.edges].all(axis=1) & self.surface_edge)
        return np.concatenate([np.asarray(nodes, np.int64), len(self.coarse.nodes) + edges]), edges

    def node_values(self, values: np.ndarray) -> np.ndarray:
        """Per-node ``values`` (N, ...) of the coarse mesh on the refined one (midpoints: the mean
        of the two ends)."""
        values = np.asarray(values)
        return np.concatenate([values, 0.5 * (values[self.edges[:, 0]] + values[self.edges[:, 1]])])

    def _set_values(self, nodes: np.ndarray, values: np.ndarray, edges: np.ndarray, combine) -> np.ndarray:
        """Values given per node of the set ``nodes`` at its midpoints ``edges``: ``combine`` of
        the two ends' rows."""
        row = {int(n): i for i, n in enumerate(nodes)}
        ends = np.array([[row[int(a)], row[int(b)]] for a, b in self.edges[edges]], np.int64).reshape(-1, 2)
        return np.concatenate([values, combine(values[ends[:, 0]], values[ends[:, 1]])])

    def constraint(self, c: Constraint) -> Constraint:
        nodes, edges = self.nodes_of(c.nodes)
        mask = self._set_values(c.nodes, c.mask, edges, np.logical_and)
        values = self._set_values(c.nodes, c.values, edges, lambda a, b: 0.5 * (a + b))
        return Constraint(nodes, mask, values, c.load_shape)

    def plate(self, plate: Plate, start_mm: np.ndarray) -> Plate:
        """``plate`` with its contact nodes' midpoints as contact nodes too, less those that start
        behind it (``start_mm`` (N', 3): the refined nodes' start positions)."""
        nodes = self.nodes_of(plate.slave_nodes)[0]
        behind = (nodes >= len(self.coarse.nodes)) & (plate.gaps(start_mm[nodes]) < -PENETRATION_TOLERANCE_MM)
        return replace(plate, slave_nodes=nodes[~behind])

    def support(self, support: SurfaceSupport) -> SurfaceSupport:
        """A surface support on the refined surface: its normals and areas made again there."""
        nodes = np.unique(self.nodes_of(support.nodes)[0])  # the order surface_normals_and_areas answers in
        normals, areas = surface_normals_and_areas(self.refined, nodes)
        return replace(support, nodes=nodes, normals=normals, areas=areas)

    def materials(self, materials: ElementMaterials) -> ElementMaterials:
        """Each element's materials on its eight children."""
        return ElementMaterials(*(np.repeat(getattr(materials, name), CHILDREN, axis=0) for name in
                                  ("mu", "kappa", "eta", "fibre", "density", "prony_g", "prony_tau")))

    def model(self, model: Model, materials: ElementMaterials | None = None,
              plates: list[Plate] | None = None) -> Model:
        """``model`` on the refined mesh (with ``materials`` and ``plates`` in place of its own
        where given): its time step is left to the solver (it halves with the edges)."""
        loading = model.loading
        prestate = (None if model.prestate is None else
                    ReferenceState(self.node_values(model.prestate.displacement), model.prestate.gravity))
        start = self.refined.nodes if prestate is None else self.refined.nodes + prestate.displacement
        refined_loading = replace(loading, constraints=[self.constraint(c) for c in loading.constraints],
                                  plates=[self.plate(p, start) for p in (loading.plates if plates is None else plates)],
                                  supports=[self.support(s) for s in loading.supports])
        mesh = TetMesh(self.refined.nodes, self.refined.tets, {},
                       {name: np.repeat(values, CHILDREN, axis=0) for name, values in model.mesh.cell_data.items()})
        return replace(model, mesh=mesh, materials=self.materials(model.materials if materials is None else materials),
                       loading=refined_loading, time_step=None, prestate=prestate)
