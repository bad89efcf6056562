"""Collapse of a closed triangle surface's short edges before it bounds a tetrahedral mesh.

Surface nets sample the body on a grid of the element edge and each vertex is then moved onto
the tissue boundary; where the boundary folds (the corners of a field of view, a thin layer) two
neighbouring vertices can land a millimetre apart. TetGen keeps every surface edge (no points are
added on the boundary), so a 1.3 mm edge among 13 mm ones makes needle elements (aspect ratio
over 10) that no node move repairs. Such an edge is collapsed to its midpoint (or, where the
midpoint is refused, to one of its ends) where that keeps the surface a closed 2-manifold (the
link condition), turns no triangle around it by more than ``max_turn_deg`` and widens no corner
there beyond ``MAX_CORNER_DEG`` (or beyond the widest corner there already); a collapse that
makes the surface cross itself is undone (:func:`without_short_edges`). Lengths in mm, in the
surface's frame.
"""

from __future__ import annotations

import numpy as np

from BreastBiomechLib.rows import unique_rows
from BreastBiomechLib.surface.trisurface import TriSurface, corner_angles

SHORT_EDGE_FRACTION = 0.3  # edges under this share of the target edge are collapsed
MAX_TURN_DEG = 35.0
MAX_CORNER_DEG = 120.0


def _normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    p = points[triangles]
    return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


def _widest_corner_deg(points: np.ndarray, triangles: np.ndarray) -> float:
    return float(corner_angles(points[triangles]).max())


def _placement(points: np.ndarray, a: int, b: int, moved: np.ndarray, before: np.ndarray, cos_turn: float,
               widest_deg: float) -> np.ndarray | None:
    """Where the point of a collapsed edge (a, b) goes: the midpoint, else the end of the two that
    keeps the surface's corners narrower, among the places that turn none of the triangles
    ``moved`` (their normals ``before``) by more than the turn limit and widen no corner past
    ``widest_deg``; None when no place does. (At the edge of a curved patch the midpoint can
    widen a corner that one end leaves as it is.)"""
    allowed = []
    for rank, place in enumerate((0.5 * (points[a] + points[b]), points[a], points[b])):
        trial = points.copy()
        trial[a] = place
        after = _normals(trial, moved)
        scale = np.linalg.norm(before, axis=1) * np.linalg.norm(after, axis=1)
        if (scale <= 0).any() or ((before * after).sum(axis=1) < cos_turn * scale).any():
            continue
        widest = _widest_corner_deg(trial, moved)
        if widest <= widest_deg:
            allowed.append((rank > 0, widest, rank, place))
    return min(allowed, key=lambda entry: entry[:3])[3] if allowed else None


def collapse_short_edges(surface: TriSurface, target_edge_mm: float, fraction: float = SHORT_EDGE_FRACTION,
                         max_turn_deg: float = MAX_TURN_DEG, frozen: np.ndarray | None = None,
                         passes: int = 4) -> tuple[TriSurface, list[tuple[int, int]], np.ndarray]:
    """``surface`` with its edges shorter than ``fraction`` x ``target_edge_mm`` collapsed where
    allowed (see the module notes), shortest first, leaving the points flagged in ``frozen`` (K,)
    alone; returns the surface (unused points dropped, orientation kept), the collapsed edges
    (kept point, removed point; indices of ``surface``) and for each point of the result its
    index in ``surface``."""
    points = surface.points.astype(float).copy()
    triangles = surface.triangles.copy()
    alive = np.ones(len(triangles), bool)
    around: list[set[int]] = [set() for _ in range(len(points))]
    for t, tri in enumerate(triangles):
        for v in tri:
            around[v].add(t)
    cos_turn = np.cos(np.radians(max_turn_deg))
    gone = np.zeros(len(points), bool) if frozen is None else np.asarray(frozen, bool).copy()
    collapsed: list[tuple[int, int]] = []
    for _ in range(passes):  # a collapse can shorten an edge next to it: pass again until none is left
        live = triangles[alive]
        edges = unique_rows(np.sort(np.concatenate([live[:, [0, 1]], live[:, [1, 2]], live[:, [2, 0]]]), axis=1))
        lengths = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)
        short = np.argsort(lengths)[: int(np.count_nonzero(lengths < fraction * target_edge_mm))]
        before_pass = len(collapsed)
        for a, b in edges[short]:
            if gone[a] or gone[b] or np.linalg.norm(points[a] - points[b]) >= fraction * target_edge_mm:
                continue
            shared = [t for t in around[a] & around[b] if alive[t]]
            if len(shared) != 2:
                continue
            ring_a = {int(v) for t in around[a] if alive[t] for v in triangles[t]} - {a}
            ring_b = {int(v) for t in around[b] if alive[t] for v in triangles[t]} - {b}
            opposite = {int(v) for t in shared for v in triangles[t]} - {a, b}
            if ring_a & ring_b != opposite:  # the link condition: else the surface would pinch
                continue
            changed = [t for t in (around[a] | around[b]) if alive[t] and t not in shared]
            before = _normals(points, triangles[changed])
            moved = triangles[changed].copy()
            moved[moved == b] = a
            if len({tuple(sorted(t)) for t in moved.tolist()}) < len(moved):  # two faces become one (a tetrahedron)
                continue
            place = _placement(points, a, b, moved, before, cos_turn,
                               max(MAX_CORNER_DEG, _widest_corner_deg(points, triangles[changed])))
            if place is None:
                continue
            points[a] = place
            triangles[changed] = moved
            alive[shared] = False
            for t in changed:
                around[a].add(t)
            around[a] -= set(shared)
            gone[b] = True
            collapsed.append((int(a), int(b)))
        if len(collapsed) == before_pass:
            break
    if not collapsed:
        return surface, [], np.arange(len(points))
    kept = triangles[alive]
    used = np.zeros(len(points), bool)
    used[kept.ravel()] = True
    index = np.cumsum(used) - 1
    return TriSurface(points[used], index[kept], surface.name), collapsed, np.flatnonzero(used)


def without_short_edges(surface: TriSurface, target_edge_mm: float, rounds: int = 4,
                        frozen: np.ndarray | None = None) -> tuple[TriSurface, int, int]:
    """``surface`` with its short edges collapsed (:func:`collapse_short_edges`), away from the
    points flagged in ``frozen``, except those whose collapse makes it cross itself: each round,
    the collapses at or next to a crossing are left out and the rest made again. Returns the
    surface, the edges collapsed and the short edges kept because collapsing them crossed the
    surface (the surface as it was when a crossing remains)."""
    from BreastBiomechLib.surface.intersections import intersecting_vertices

    frozen = np.zeros(len(surface.points), bool) if frozen is None else np.asarray(frozen, bool).copy()
    refused = 0
    for _ in range(rounds):
        shorter, pairs, origin = collapse_short_edges(surface, target_edge_mm, frozen=frozen)
        if not pairs:
            return surface, 0, refused
        bad = intersecting_vertices(shorter)
        if len(bad) == 0:
            return shorter, len(pairs), refused
        near = np.zeros(len(shorter.points), bool)
        near[bad] = True
        near[np.unique(shorter.triangles[near[shorter.triangles].any(axis=1)])] = True  # and their neighbours
        near_original = set(origin[near].tolist())
        undo = [(a, b) for a, b in pairs if a in near_original]
        if not undo:  # the crossing is not of these collapses' making
            return surface, 0, refused
        for a, b in undo:
            frozen[a] = frozen[b] = True
        refused += len(undo)
    return surface, 0, refused
