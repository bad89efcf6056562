"""Surfaces of tissue regions in a label image: surface nets on the (slightly blurred) binary
mask sampled at the target edge length, with constrained smoothing, vertices projected back onto
the full-resolution boundary, normals outwards.

The label image is a SimpleITK image with the values of :mod:`BreastBiomechLib.labels`. The mask
is padded with background before extraction, so a region cut by the field of view gets a flat
cap there and its surface is always closed. Output points in LPS mm (the image's physical
space, any direction matrix)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from BreastBiomechLib.labels import BY_LABEL
from BreastBiomechLib.surface.trisurface import TriSurface, corner_angles

_PAD = 2  # background voxels added on every side


class RegionTooThin(ValueError):
    """A region that no sample of the coarse surface grid falls inside: it is smaller or
    thinner than the surface spacing."""


@dataclass
class SurfaceSettings:
    """How surfaces are made. ``edge_mm``: target triangle edge (the outer surface; tissue
    interfaces use the mesher's own value); ``blur_mm``: Gaussian sigma applied to the binary
    mask (removes the voxel staircase; 0 for none); ``smoothing_iterations`` of the surface nets'
    constrained smoothing (shapes the triangles); ``min_component_mm3``: pieces of a tissue
    smaller than this are dropped."""

    edge_mm: float = 3.0
    blur_mm: float = 0.8
    smoothing_iterations: int = 30
    min_component_mm3: float = 20.0

    def __post_init__(self) -> None:
        if self.edge_mm <= 0:
            raise ValueError("the surface edge length must be positive (mm)")
        if self.blur_mm < 0 or self.smoothing_iterations < 0:
            raise ValueError("blur_mm and smoothing_iterations must be >= 0")


def label_array(labels: sitk.Image) -> np.ndarray:
    """The label image's voxels (z, y, x) as integers; a clear error for images that are not a
    3D scalar label map."""
    if labels.GetDimension() != 3:
        raise ValueError(f"the label map must be a 3D image, this one has {labels.GetDimension()} dimensions")
    if labels.GetNumberOfComponentsPerPixel() != 1:
        raise ValueError("the label map must have one value per voxel, not a vector image")
    array = sitk.GetArrayViewFromImage(labels)
    if np.issubdtype(array.dtype, np.floating):
        if not np.all(np.mod(array, 1) == 0):
            raise ValueError("the label map holds non-integer values; pass a label image (values of the label table)")
    return np.asarray(array).astype(np.int32, copy=False)


def index_to_physical(labels: sitk.Image) -> tuple[np.ndarray, np.ndarray]:
    """Matrix A (3, 3) and origin o with physical = o + A @ (i, j, k) for continuous voxel
    indices (i along x)."""
    direction = np.asarray(labels.GetDirection(), float).reshape(3, 3)
    return direction * np.asarray(labels.GetSpacing(), float)[None, :], np.asarray(labels.GetOrigin(), float)


def largest_component(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """The largest 6-connected piece of ``mask`` and how many voxels the other pieces held."""
    components, count = ndimage.label(mask)
    if count <= 1:
        return mask, 0
    sizes = np.bincount(components.ravel())
    sizes[0] = 0
    keep = int(np.argmax(sizes))
    return components == keep, int(sizes.sum() - sizes[keep])


def _drop_small(mask: np.ndarray, min_voxels: int) -> np.ndarray:
    components, count = ndimage.label(mask)
    if count == 0:
        return mask
    sizes = np.bincount(components.ravel())
    keep = sizes >= min_voxels
    keep[0] = False
    return keep[components]


def mask_surface(mask: np.ndarray, geometry: sitk.Image, name: str, settings: SurfaceSettings,
                 edge_mm: float | None = None, notes: list[str] | None = None, untangle: bool = False) -> TriSurface:
    """Closed surface of a boolean mask (z, y, x) on ``geometry``'s grid with triangles of about
    ``edge_mm`` (default the settings' edge): surface nets on the blurred mask sampled on an
    isotropic grid of that spacing (well-shaped triangles, no slivers), each vertex then moved
    onto the 0.5 level of the blurred mask on the full-resolution grid (so the coarse sampling
    and the smoothing do not shrink the region). With ``untangle`` (a surface that bounds a
    mesh), not where that would make the surface cross itself (:func:`untangled`; a sentence
    saying so is appended to ``notes``)."""
    import vtk
    from vtk.util import numpy_support as nps

    if not mask.any():
        raise ValueError(f"{name}: the mask is empty, there is no surface to extract")
    edge = settings.edge_mm if edge_mm is None else float(edge_mm)
    spacing_xyz = np.asarray(geometry.GetSpacing(), float)
    padded = np.pad(mask.astype(np.float32), _PAD)
    sigma_zyx = spacing_xyz[::-1]
    # two blurred masks: the fine one's 0.5 level is the surface; the wide one (sigma half the
    # edge) has a gradient far enough out to pull the coarse vertices in, and is what is sampled
    fine = ndimage.gaussian_filter(padded, settings.blur_mm / sigma_zyx, mode="constant", truncate=3.0) \
        if settings.blur_mm > 0 else padded
    wide = ndimage.gaussian_filter(padded, max(settings.blur_mm, 0.5 * edge) / sigma_zyx, mode="constant",
                                   truncate=3.0)
    step = edge / spacing_xyz  # coarse isotropic samples, in the padded grid's index units (x, y, z)
    counts = np.ceil((np.array(padded.shape[::-1]) - 1) / step).astype(int) + 1
    axes = [np.arange(n) * s for n, s in zip(counts, step)]
    zz, yy, xx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    coarse = ndimage.map_coordinates(wide, [zz, yy, xx], order=1) > 0.5
    if not coarse.any():
        raise RegionTooThin(f"{name}: the region is thinner than the {edge:g} mm surface spacing; use a smaller edge")
    coarse = np.pad(well_composed(coarse), 1).astype(np.uint8)
    image = vtk.vtkImageData()
    image.SetDimensions(coarse.shape[2], coarse.shape[1], coarse.shape[0])
    image.SetSpacing(*step)
    image.SetOrigin(*(-step))
    image.GetPointData().SetScalars(nps.numpy_to_vtk(coarse.ravel(), deep=True))
    nets = vtk.vtkSurfaceNets3D()
    nets.SetInputData(image)
    nets.SetLabel(0, 1)
    nets.SetBackgroundLabel(0)
    nets.SetOutputMeshTypeToTriangles()
    nets.SetNumberOfIterations(settings.smoothing_iterations)
    # VTK 9.5's surface nets (the VTK of Slicer 5.10) winds some triangles against their
    # neighbours (VTK 9.6's does not): make the winding consistent, points untouched
    consistent = vtk.vtkPolyDataNormals()
    consistent.SetInputConnection(nets.GetOutputPort())
    consistent.SplittingOff()
    consistent.ConsistencyOn()
    consistent.AutoOrientNormalsOff()
    consistent.Update()
    surface = TriSurface.from_vtk(consistent.GetOutput(), name)
    if len(surface.triangles) == 0:
        raise ValueError(f"{name}: no surface at a {edge:g} mm spacing; use a smaller edge")
    ijk = _relaxed_onto_level((wide, fine), surface, max_move=step)
    A, origin = index_to_physical(geometry)
    nets_points = origin + (surface.points - _PAD) @ A.T
    surface = flip_obtuse_triangles(TriSurface(origin + (ijk - _PAD) @ A.T, surface.triangles, name))
    surface, pulled = untangled(surface, nets_points, edge) if untangle else (surface, 0)
    if pulled and notes is not None:
        notes.append(f"{name}: {pulled} surface points kept nearer the sampled surface, where moving them onto "
                     f"the boundary would make the surface cross itself (tissue thinner than the {edge:g} mm spacing)")
    return surface if surface.volume_mm3 > 0 else surface.flipped()


def untangled(surface: TriSurface, fallback: np.ndarray, edge_mm: float, rounds: int = 6) -> tuple[TriSurface, int]:
    """``surface`` with the points of every pair of crossing triangles (and their neighbours)
    moved halfway back to their ``fallback`` positions (K, 3) (the surface nets' points, which
    lie in their own sampling cells), round after round, and at last onto them; returns the
    surface and how many points moved. A ValueError names where the surface still crosses
    itself when even the fallback positions do."""
    from scipy.sparse import coo_matrix

    from BreastBiomechLib.surface.intersections import SurfaceCrossesItself, intersecting_vertices

    tri = surface.triangles
    n = len(surface.points)
    rows, cols = tri[:, [0, 1, 2, 1, 2, 0]].ravel(), tri[:, [1, 2, 0, 0, 1, 2]].ravel()
    adjacency = coo_matrix((np.ones(len(rows), bool), (rows, cols)), shape=(n, n)).tocsr()
    points = surface.points.copy()
    moved = np.zeros(n, bool)
    for round_ in range(rounds + 1):
        bad = intersecting_vertices(TriSurface(points, tri, surface.name))
        if len(bad) == 0:
            return TriSurface(points, tri, surface.name), int(moved.sum())
        if round_ == rounds:
            break
        ring = np.zeros(n, bool)
        ring[bad] = True
        ring |= np.asarray(adjacency[bad].sum(axis=0)).ravel() > 0
        points[ring] = fallback[ring] if round_ == rounds - 1 else 0.5 * (points[ring] + fallback[ring])
        moved |= ring
    where = np.round(points[bad].mean(axis=0), 1).tolist()
    raise SurfaceCrossesItself(f"{surface.name}: the surface crosses itself near {where} mm (LPS) even at its sampled "
                     f"positions: the tissue there is thinner than the {edge_mm:g} mm spacing; use a smaller edge "
                     "or a larger blur")


def flip_obtuse_triangles(surface: TriSurface, limit_deg: float = 130.0) -> TriSurface:
    """Flip the edge opposite each corner wider than ``limit_deg`` where that lowers the widest
    corner of both triangles (the few obtuse triangles the relaxation leaves would give elements
    with face angles over 150 degrees). Orientation and manifoldness are kept."""
    tri = surface.triangles.copy()
    widest = corner_angles(surface.points[tri]).max(axis=1)
    if not (widest > limit_deg).any():
        return surface
    edges = {}
    for t, (a, b, c) in enumerate(tri):
        for u, v in ((a, b), (b, c), (c, a)):
            edges[(u, v)] = t
    for t in np.flatnonzero(widest > limit_deg):
        angles = corner_angles(surface.points[tri[t]])
        k = int(np.argmax(angles))
        c, a, b = tri[t][k], tri[t][(k + 1) % 3], tri[t][(k + 2) % 3]  # edge a->b opposite c
        other = edges.get((b, a))
        if other is None:
            continue
        d = [x for x in tri[other] if x not in (a, b)][0]
        if (c, d) in edges or (d, c) in edges:
            continue  # the flipped edge exists already: flipping would make it non-manifold
        new = np.array([(a, d, c), (d, b, c)])
        old_worst = max(angles.max(), corner_angles(surface.points[tri[other]]).max())
        if corner_angles(surface.points[new]).max() >= old_worst:
            continue
        for u, v in ((a, b), (b, c), (c, a)):
            edges.pop((u, v), None)
        for u, v in ((b, a), (a, d), (d, b)):
            edges.pop((u, v), None)
        tri[t], tri[other] = new
        for index in (t, other):
            x, y, z = tri[index]
            for u, v in ((x, y), (y, z), (z, x)):
                edges[(u, v)] = index
    return TriSurface(surface.points, tri, surface.name)


def well_composed(mask: np.ndarray, max_rounds: int = 100) -> np.ndarray:
    """``mask`` with voxels added until it has none of the critical configurations whose
    surface is not a manifold (Latecki's well-composed images): in any 2x2 square two voxels
    set only on a diagonal, and in any 2x2x2 cube two voxels set, or two unset, only on a body
    diagonal. Only adds voxels, so it ends."""
    m = mask.copy()
    for _ in range(max_rounds):
        fixed = False
        for u, v in ((0, 1), (0, 2), (1, 2)):
            def at(du, dv):
                index = [slice(None)] * 3
                index[u] = slice(du, m.shape[u] - 1 + du)
                index[v] = slice(dv, m.shape[v] - 1 + dv)
                return tuple(index)
            a, b, c, d = m[at(0, 0)], m[at(1, 0)], m[at(0, 1)], m[at(1, 1)]
            critical = (a & d & ~b & ~c) | (b & c & ~a & ~d)
            if critical.any():
                fixed = True
                for du, dv in ((0, 0), (1, 0), (0, 1), (1, 1)):
                    m[at(du, dv)] |= critical
        corners = [(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)]

        def cube(c):
            return tuple(slice(c[a], m.shape[a] - 1 + c[a]) for a in range(3))

        values = {c: m[cube(c)] for c in corners}
        count = sum(v.astype(np.int8) for v in values.values())
        for c in corners[:4]:
            opposite = tuple(1 - x for x in c)
            pair = values[c] & values[opposite]
            none_of_pair = ~values[c] & ~values[opposite]
            critical = (pair & (count == 2)) | (none_of_pair & (count == 6))
            if critical.any():
                fixed = True
                for corner in corners:
                    m[cube(corner)] |= critical
        if not fixed:
            return m
    raise RuntimeError("could not make the sampled mask well-composed; use a smaller edge or more blur")


def _relaxed_onto_level(fields: tuple[np.ndarray, np.ndarray], surface: TriSurface, max_move: np.ndarray,
                        rounds: int = 3) -> np.ndarray:
    """The surface's points (index units) moved onto the 0.5 level of the fine field (fields =
    (wide, fine) blurred masks: the wide one first, whose gradient reaches further), alternating
    with Laplacian relaxation (each point halfway to the mean of its neighbours), which evens the
    triangles out again after each projection; returns the points."""
    from scipy.sparse import coo_matrix

    tri = surface.triangles
    rows = np.concatenate([tri[:, 0], tri[:, 1], tri[:, 2], tri[:, 1], tri[:, 2], tri[:, 0]])
    cols = np.concatenate([tri[:, 1], tri[:, 2], tri[:, 0], tri[:, 0], tri[:, 1], tri[:, 2]])
    adjacency = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(surface.points),) * 2).tocsr()
    adjacency.data[:] = 1.0
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    gradients = [[np.gradient(f, axis=a) for a in (2, 1, 0)] for f in fields]
    start = surface.points.copy()
    points = start
    for round_ in range(rounds + 1):
        if round_:
            points = 0.5 * points + 0.5 * (adjacency @ points) / degree[:, None]
        for field, gradient in zip(fields, gradients):
            points = _onto_level(field, gradient, points, start, max_move)
    return points


def _onto_level(field: np.ndarray, gradient: list[np.ndarray], ijk: np.ndarray, start: np.ndarray,
                max_move: np.ndarray, level: float = 0.5, iterations: int = 6) -> np.ndarray:
    """Newton steps moving points (K, 3) in index units (x, y, z) along the gradient (d/dx,
    d/dy, d/dz arrays) of the trilinearly interpolated ``field`` (z, y, x) onto its ``level``
    set; no point moves more than ``max_move`` per axis from ``start`` (K, 3)."""
    points = ijk.copy()
    for _ in range(iterations):
        where = [points[:, 2], points[:, 1], points[:, 0]]
        value = ndimage.map_coordinates(field, where, order=1) - level
        g = np.stack([ndimage.map_coordinates(d, where, order=1) for d in gradient], axis=1)
        norm2 = np.maximum((g**2).sum(axis=1), 1e-6)
        points = points - (value / norm2)[:, None] * g
        points = np.clip(points, start - max_move, start + max_move)
    return points


def body_surface(labels: sitk.Image, settings: SurfaceSettings | None = None,
                 notes: list[str] | None = None) -> tuple[TriSurface, int]:
    """The outer surface of every labelled voxel (the whole model: breast and muscle), its
    largest connected piece, free of self-intersections (:func:`untangled`; the repair is
    described in ``notes``); returns the surface and the number of voxels in other pieces that
    were left out (islands)."""
    settings = settings or SurfaceSettings()
    array = label_array(labels)
    body = array > 0
    if not body.any():
        raise ValueError("the label map has no labelled voxels (all background); segment the breast first")
    body, dropped = largest_component(body)
    return mask_surface(body, labels, "body", settings, notes=notes, untangle=True), dropped


def tissue_surface(labels: sitk.Image, label: int, edge_mm: float,
                   settings: SurfaceSettings | None = None) -> TriSurface | None:
    """Surface of the voxels of one tissue label (all its pieces of at least
    ``settings.min_component_mm3``) with triangles of about ``edge_mm``; None when the tissue is
    absent. (Its points refine the mesh: it need not be free of self-intersections.)"""
    settings = settings or SurfaceSettings()
    mask = label_array(labels) == label
    voxel_mm3 = float(np.prod(labels.GetSpacing()))
    mask = _drop_small(mask, max(1, int(np.ceil(settings.min_component_mm3 / voxel_mm3))))
    if not mask.any():
        return None

    name = BY_LABEL[label].name if label in BY_LABEL else f"label {label}"
    return mask_surface(mask, labels, name, settings, edge_mm)
