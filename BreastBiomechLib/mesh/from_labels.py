"""From a tissue label map to a tetrahedral breast mesh (the seed's sections 2.2.2-2.2.4): body
surface, interface points of each internal tissue, TetGen, repair of the few poor boundary
elements, tissue per element by voxel majority, quality report and loading node sets.

Input: a SimpleITK label image with the values of :mod:`BreastBiomechLib.labels` (0
background); output geometry in LPS mm."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import SimpleITK as sitk

from BreastBiomechLib import labels as lt
from BreastBiomechLib.mesh.improve import improve_quality
from BreastBiomechLib.mesh.node_sets import breast_node_sets
from BreastBiomechLib.mesh.quality import QualityReport, mesh_quality
from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.mesh.tissues import TissueAssignment, assign_tissues
from BreastBiomechLib.mesh.volume import TetGenSettings, interface_points, tetrahedralize
from BreastBiomechLib.surface.extract import RegionTooThin, SurfaceSettings, body_surface, label_array, tissue_surface
from BreastBiomechLib.surface.intersections import SurfaceCrossesItself
from BreastBiomechLib.surface.trisurface import TriSurface
from BreastBiomechLib.timing import staged

_RETRIES = 2  # finer body surfaces tried when TetGen finds the surface intersecting itself
REMAKE_FACTOR = 0.9  # the body surface's edge, as a fraction of the asked, tried where failing elements remain


@dataclass
class MeshSettings:
    """Everything that shapes the mesh. ``edge_mm`` sets the element size in the interior and on
    the outer surface, ``surface_edge_mm`` the outer surface's triangles where they should be
    finer (None: ``edge_mm``; a skin compared with the measured one, under a coarse interior);
    ``interface_edge_mm`` the spacing of the points inserted on tissue
    interfaces (None: ``edge_mm``); ``refine_interfaces`` False meshes the body alone (tissues
    then follow the voxel majority only); ``blur_mm``, quality bounds as in
    :class:`~BreastBiomechLib.surface.SurfaceSettings` and
    :class:`~BreastBiomechLib.mesh.volume.TetGenSettings`."""

    edge_mm: float = 3.0
    surface_edge_mm: float | None = None
    interface_edge_mm: float | None = None
    refine_interfaces: bool = True
    blur_mm: float = 0.8
    min_radius_edge: float = 1.5
    min_dihedral_deg: float = 12.0
    min_component_mm3: float = 20.0

    def surface(self) -> SurfaceSettings:
        return SurfaceSettings(edge_mm=self.edge_mm if self.surface_edge_mm is None else self.surface_edge_mm,
                               blur_mm=self.blur_mm,
                               min_component_mm3=self.min_component_mm3)

    def tetgen(self) -> TetGenSettings:
        return TetGenSettings(edge_mm=self.edge_mm, interface_edge_mm=self.interface_edge_mm,
                              min_radius_edge=self.min_radius_edge, min_dihedral_deg=self.min_dihedral_deg)


@dataclass
class BreastMesh:
    """The mesh (cell data: ``tissue``, ``fraction_<tissue>``, ``quality_*``; point data: the
    node sets) and how it was made: surfaces, quality, tissue assignment, timings (s) and notes
    on repairs."""

    mesh: TetMesh
    surfaces: dict[str, TriSurface]
    quality: QualityReport
    assignment: TissueAssignment
    representation: dict[str, dict[str, float]]
    seconds: dict[str, float]
    notes: list[str] = field(default_factory=list)

    def summary(self) -> dict:
        """A JSON-ready summary: sizes, element counts per tissue, quality, representation."""
        return {
            "nodes": len(self.mesh.nodes), "elements": len(self.mesh.tets),
            "volume_cm3": float(self.mesh.volumes.sum() / 1000.0),
            "elements_per_tissue": self.assignment.counts(),
            "node_sets": {name: int(np.count_nonzero(v)) for name, v in self.mesh.point_data.items()},
            "quality": self.quality.summary(),
            "tissue_representation": self.representation,
            "surfaces": {name: {"triangles": len(s.triangles), "volume_cm3": s.volume_mm3 / 1000.0}
                         for name, s in self.surfaces.items()},
            "seconds": self.seconds, "notes": self.notes,
        }


def _body_surface(labels: sitk.Image, settings: SurfaceSettings, notes: list[str]) -> tuple[TriSurface, int]:
    """:func:`body_surface`, made with finer triangles (up to ``_RETRIES`` times 0.7 the edge)
    where even its repair leaves it crossing itself (a part of the body thinner than the edge)."""
    for attempt in range(_RETRIES + 1):
        try:
            return body_surface(labels, settings, notes)
        except SurfaceCrossesItself as error:
            if attempt == _RETRIES:
                raise SurfaceCrossesItself(f"{error} (also at {settings.edge_mm:.1f} mm)") from None
            notes.append(f"{error}; remade at {0.7 * settings.edge_mm:.1f} mm")
            settings = replace(settings, edge_mm=0.7 * settings.edge_mm)
    raise AssertionError("unreachable")


def _without_short_edges(body: TriSurface, edge_mm: float, notes: list[str]) -> TriSurface:
    """The body surface with its short edges collapsed where that keeps it from crossing itself
    (:func:`~BreastBiomechLib.surface.collapse.without_short_edges`: TetGen keeps every surface
    edge, and one much shorter than the element edge makes needle elements); said in ``notes``."""
    from BreastBiomechLib.surface.collapse import SHORT_EDGE_FRACTION, without_short_edges
    from BreastBiomechLib.surface.extract import flip_obtuse_triangles

    shorter, collapsed, refused = without_short_edges(body, edge_mm)
    if collapsed or refused:
        notes.append(f"body: {collapsed} surface edges under {SHORT_EDGE_FRACTION * edge_mm:.1f} mm collapsed "
                     "(they would make needle elements)" + (f", {refused} kept where collapsing them would make the "
                                                           "surface cross itself" if refused else ""))
    return flip_obtuse_triangles(shorter) if collapsed else body


def _interface_surface(labels: sitk.Image, value: int, name: str, spacing: float, settings: SurfaceSettings,
                       notes: list[str]) -> TriSurface | None:
    """The surface of one tissue whose points refine the mesh, at ``spacing`` mm; a tissue
    smaller than that (a 12 mm tumour under 10 mm elements) is sampled at a third of its
    equivalent diameter instead, which refines the mesh around it (said in ``notes``)."""
    try:
        return tissue_surface(labels, value, spacing, settings)
    except RegionTooThin:
        voxels = int(np.count_nonzero(label_array(labels) == value))
        diameter = (6.0 * voxels * float(np.prod(labels.GetSpacing())) / np.pi) ** (1.0 / 3.0)
        finer = max(diameter / 3.0, min(labels.GetSpacing()))
        notes.append(f"{name}: smaller than the {spacing:g} mm interface spacing ({diameter:.0f} mm across); "
                     f"its surface points at {finer:.1f} mm refine the mesh around it")
        try:
            return tissue_surface(labels, value, finer, settings)
        except RegionTooThin:
            notes.append(f"{name}: too thin to sample even at {finer:.1f} mm; elements take it by voxel majority only")
            return None



def _repaired_volume_mesh(labels: sitk.Image, body: TriSurface, interfaces: list[TriSurface],
                          surface_settings: SurfaceSettings, tetgen_settings: TetGenSettings,
                          notes: list[str]) -> tuple[TetMesh, TriSurface, QualityReport]:
    """TetGen's mesh of ``body`` (short edges collapsed; remade finer, up to ``_RETRIES`` times,
    where TetGen finds it intersecting itself) refined by the ``interfaces``' points, repaired
    (:func:`improve_quality`); returns the mesh, the body surface it was made from and its
    quality report. What was done goes to ``notes``."""
    spacing = tetgen_settings.interface_spacing_mm
    attempt, edge = 0, surface_settings.edge_mm
    bound = _without_short_edges(body, edge, notes)
    while True:
        points = interface_points(bound, interfaces, spacing, tetgen_settings.boundary_clearance * spacing)
        try:
            mesh = tetrahedralize(bound, points, tetgen_settings)
            break
        except RuntimeError as error:
            if "self-intersect" not in str(error):
                raise
            if bound is not body:  # TetGen is stricter than the collapses' own check: mesh without them
                notes.append("TetGen found the body surface with its short edges collapsed touching itself; "
                             "meshed it without the collapses")
                bound = body
                continue
            # a surface coarser than a thin part of the body (a chest layer at the edge of the
            # field of view) can touch itself there: retry with finer triangles
            if attempt == _RETRIES:
                raise
            attempt, edge = attempt + 1, body.mean_edge_mm * 0.7
            notes.append(f"TetGen found the body surface intersecting itself at a {body.mean_edge_mm:.1f} mm edge; "
                         f"remade it at {edge:.1f} mm")
            body, _ = _body_surface(labels, replace(surface_settings, edge_mm=edge), notes)
            bound = _without_short_edges(body, edge, notes)
    mesh, repairs = improve_quality(mesh)
    if repairs["poor_before"] or repairs["caps_removed"] or repairs["nodes_moved"]:
        notes.append(f"{repairs['poor_before']} poor elements after TetGen; {repairs['caps_removed']} flat or poor "
                     f"boundary caps removed, {repairs['peeled']} poor elements peeled off the surface, "
                     f"{repairs['edges_collapsed']} short edges collapsed, {repairs['nodes_moved']} nodes moved; "
                     f"{repairs['poor_after']} poor elements and {repairs['slivers_after']} interior slivers "
                     "(under 10 degrees) left")
    return mesh, bound, mesh_quality(mesh)


@staged("meshing")
def mesh_labels(labels: sitk.Image, settings: MeshSettings | None = None, nipple_mm=None,
                progress: Callable[[float, str], None] | None = None) -> BreastMesh:
    """Mesh the labelled region of ``labels`` (see the module notes). ``nipple_mm`` (3,) LPS
    places the nipple node (default: the most anterior skin node). ``progress(fraction,
    message)`` is called between stages."""
    settings = settings or MeshSettings()
    report = progress or (lambda fraction, message: None)
    seconds, notes = {}, []
    clock = time.perf_counter()

    def lap(name):
        nonlocal clock
        now = time.perf_counter()
        seconds[name] = round(now - clock, 3)
        clock = now

    array = label_array(labels)
    present = lt.present_labels(array)
    report(0.0, "body surface")
    surface_settings = settings.surface()
    body, islands = _body_surface(labels, surface_settings, notes)
    if islands:
        notes.append(f"{islands} labelled voxels outside the largest connected region were left out")
    surfaces = {"body": body}
    lap("body_surface")

    report(0.15, "tissue surfaces")
    tetgen_settings = settings.tetgen()
    spacing = tetgen_settings.interface_spacing_mm
    voxel_mm3 = float(np.prod(labels.GetSpacing()))
    for value in present:
        if value == lt.FAT.label or not settings.refine_interfaces:
            continue
        name = lt.BY_LABEL[value].name
        surface = _interface_surface(labels, value, name, spacing, surface_settings, notes)
        if surface is None:
            count = int(np.count_nonzero(array == value))
            notes.append(f"{name}: {count} voxels ({count * voxel_mm3:.0f} mm3), no piece of "
                         f"{settings.min_component_mm3:g} mm3 or more; not used to refine the mesh")
            continue
        surfaces[name] = surface
    lap("tissue_surfaces")

    report(0.3, "TetGen")
    interfaces = [s for n, s in surfaces.items() if n != "body"]
    made = _repaired_volume_mesh(labels, body, interfaces, surface_settings, tetgen_settings, notes)
    failing = int(made[2].failing()["any"].sum())
    if failing:
        # elements the repair could not mend (a face left flat where removed caps exposed it): a
        # body surface sampled a little finer meshes differently
        edge, trial_notes = REMAKE_FACTOR * surface_settings.edge_mm, []
        finer = replace(surface_settings, edge_mm=edge)
        try:
            remade = _repaired_volume_mesh(labels, _body_surface(labels, finer, trial_notes)[0], interfaces, finer,
                                           tetgen_settings, trial_notes)
        except (RuntimeError, ValueError) as error:
            remade, trial_notes = None, [f"remaking it failed: {error}"]
        left = None if remade is None else int(remade[2].failing()["any"].sum())
        if left is not None and left < failing:
            notes.append(f"{failing} element(s) failing the quality criteria after the repair; the body surface "
                         f"remade at {edge:.1f} mm left {left}")
            notes.extend(trial_notes)
            made = remade
        else:
            notes.append(f"{failing} element(s) failing the quality criteria after the repair; remaking the body "
                         f"surface at {edge:.1f} mm did not leave fewer"
                         + (f" ({trial_notes[0]})" if remade is None else ""))
    mesh, surfaces["body"], quality = made
    lap("tetgen_and_repair")

    report(0.7, "tissue per element")
    assignment = assign_tissues(mesh, labels)
    representation = assignment.representation(labels)
    lap("tissues")
    report(0.85, "node sets")
    node_sets = breast_node_sets(mesh, assignment.tissue, labels, nipple_mm)
    lap("node_sets")
    mesh = TetMesh(mesh.nodes, mesh.tets, point_data=node_sets,
                   cell_data={**assignment.cell_data(), **quality.cell_data()})
    seconds["total"] = round(sum(seconds.values()), 3)
    report(1.0, "done")
    return BreastMesh(mesh, surfaces, quality, assignment, representation, seconds, notes)
