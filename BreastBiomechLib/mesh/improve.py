"""Repair of the few poor elements TetGen leaves at a curved boundary: flat caps (elements with
two or three faces on the surface, which lie almost in it: all four nodes on the surface, so a
plate that flattens the surface there flattens them to zero volume) are removed, poor elements
with one face on the surface peeled off, needles (an edge a fifth of the element's longest) and
flat faces (a corner over 150 degrees) collapsed, and the nodes of the remaining poor elements
and of interior slivers (under 10 degrees, which pass the seed's criteria but invert under a
plate) are moved towards their neighbours (boundary nodes along the surface) where that improves
every element around them (smart Laplacian smoothing), round after round while any remain.
Nodes in LPS mm."""

from __future__ import annotations

import numpy as np

from BreastBiomechLib.mesh.quality import QualityReport, element_measures, mesh_quality
from BreastBiomechLib.mesh.tetmesh import TetMesh, boundary_faces, boundary_nodes, signed_volumes, signed_volumes_of
from BreastBiomechLib.rows import unique_rows


def boundary_face_counts(tets: np.ndarray) -> np.ndarray:
    """Number of faces (0-4) of each element that lie on the mesh boundary."""
    return np.bincount(boundary_faces(tets)[1], minlength=len(tets))


def _scores_at(nodes: np.ndarray, tets: np.ndarray, node: int, positions: np.ndarray,
               min_dihedral_deg: float) -> np.ndarray:
    """The worst element of ``tets`` (the smoothing's acceptance test) with ``node`` at each of
    ``positions`` (T, 3) in turn, all measured at once: its shape factor, halved if it is poor,
    -1 if an element is inverted."""
    p = np.broadcast_to(nodes[tets], (len(positions), len(tets), 4, 3)).copy()
    p[:, tets == node] = positions[:, None, :]
    p = p.reshape(-1, 4, 3)
    volume = signed_volumes_of(p)
    report = QualityReport(*element_measures(p))
    poor = report.failing()["any"] | (report.min_dihedral_deg < min_dihedral_deg)
    worst = (report.shape_factor * np.where(poor, 0.5, 1.0)).reshape(len(positions), -1).min(axis=1)
    return np.where((volume <= 0).reshape(len(positions), -1).any(axis=1), -1.0, worst)


def _rank(nodes: np.ndarray, tets: np.ndarray, min_dihedral_deg: float) -> tuple[int, float]:
    """How good ``tets`` are, for comparing the elements around a collapse (larger is better):
    minus the number of poor elements, then the worst element as :func:`_scores_at` scores it. A
    collapse that leaves no element poor is taken even where its worst element's shape factor
    falls (it stays above the poor limit); an inverted element ranks below everything."""
    if (signed_volumes(nodes, tets) <= 0).any():
        return (-len(tets) - 1, -1.0)
    report = mesh_quality(TetMesh(nodes, tets))
    poor = report.failing()["any"] | (report.min_dihedral_deg < min_dihedral_deg)
    return (-int(poor.sum()), float((report.shape_factor * np.where(poor, 0.5, 1.0)).min()))


def _apex_edges_inside(tets: np.ndarray, which: np.ndarray) -> np.ndarray:
    """For elements ``which`` with one face on the boundary: whether none of the three edges from
    the node off that face to the face's nodes is an edge of a boundary face."""
    faces, owner = boundary_faces(tets)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    on_surface = {tuple(e) for e in edges}
    face_of = dict(zip(owner, faces))
    result = np.ones(len(which), bool)
    for k, element in enumerate(which):
        apex = [n for n in tets[element] if n not in face_of[element]][0]
        result[k] = not any(tuple(sorted((apex, n))) in on_surface for n in face_of[element])
    return result


def _ideal_apex(nodes: np.ndarray, tet: np.ndarray, node: int) -> np.ndarray:
    """Where ``node`` would make ``tet`` regular-like: above the centroid of the opposite face, on
    the side it is now, at the height of a regular tet on that face's mean edge."""
    base = nodes[[n for n in tet if n != node]]
    centre = base.mean(axis=0)
    normal = np.cross(base[1] - base[0], base[2] - base[0])
    normal /= np.linalg.norm(normal)
    if (nodes[node] - centre) @ normal < 0:
        normal = -normal
    edge = np.mean([np.linalg.norm(base[i] - base[j]) for i, j in ((0, 1), (0, 2), (1, 2))])
    return centre + normal * edge * np.sqrt(2.0 / 3.0)


def improve_quality(mesh: TetMesh, min_dihedral_deg: float = 5.0, cap_dihedral_deg: float = 15.0,
                    sliver_dihedral_deg: float = 10.0, rounds: int = 3) -> tuple[TetMesh, dict]:
    """:func:`improve_once` repeated while poor elements or interior slivers remain (``rounds``
    at most): each round peels what the last left at the boundary and smooths around the rest.
    Returns the mesh and the totals of what was done, ``poor_before`` the poor elements TetGen
    left, ``poor_after`` those that remain and ``slivers_after`` the interior slivers."""
    totals = {"caps_removed": 0, "peeled": 0, "edges_collapsed": 0, "nodes_moved": 0}
    poor_before = None
    for _ in range(rounds):
        mesh, done = improve_once(mesh, min_dihedral_deg, cap_dihedral_deg, sliver_dihedral_deg)
        poor_before = done["poor_before"] if poor_before is None else poor_before
        for key in totals:
            totals[key] += done[key]
        report = mesh_quality(mesh)
        poor_after = int((report.failing()["any"] | (report.min_dihedral_deg < min_dihedral_deg)).sum())
        slivers_after = int(_interior_slivers(mesh.tets, report, sliver_dihedral_deg).sum())
        if poor_after + slivers_after == 0 or not (done["caps_removed"] or done["peeled"] or done["edges_collapsed"]
                                                   or done["nodes_moved"]):
            break
    return mesh, {**totals, "poor_before": poor_before, "poor_after": poor_after, "slivers_after": slivers_after}


def _interior_slivers(tets: np.ndarray, report, sliver_dihedral_deg: float) -> np.ndarray:
    """Elements with no face on the boundary and a dihedral angle under ``sliver_dihedral_deg``:
    four nodes almost in a plane, which pass the seed's criteria but turn inside out when a load
    presses across that plane (a 5.9-degree sliver under a plate inverted in the first second of
    a coarse fitting mesh's solve)."""
    return (boundary_face_counts(tets) == 0) & (report.min_dihedral_deg < sliver_dihedral_deg)


def improve_once(mesh: TetMesh, min_dihedral_deg: float = 5.0,
                 cap_dihedral_deg: float = 15.0, sliver_dihedral_deg: float = 10.0) -> tuple[TetMesh, dict]:
    """One round of repair: ``mesh`` with its poor elements (failing the seed's criteria, or
    slivers with a dihedral angle below ``min_dihedral_deg``) repaired: those with two or more
    faces on the boundary removed, as is every such cap flatter than ``cap_dihedral_deg`` (its smallest dihedral
    angle: a cap of 5.5 degrees on the skin of a suite anatomy's fitting mesh passed the poor
    criteria and inverted under the plate in every solve near the fit), those with one face on
    it and their fourth node inside peeled off, the nodes of the others and of the interior
    slivers (:func:`_interior_slivers`) moved where that improves every element around them
    (boundary nodes only towards their surface neighbours, at most halfway). Returns the mesh (unused nodes dropped, so node ids
    change) and what was done: ``caps_removed``, ``peeled``, ``nodes_moved``, ``poor_before``."""
    from scipy.sparse import csr_matrix

    nodes = mesh.nodes.copy()
    report = mesh_quality(TetMesh(nodes, mesh.tets))
    poor = report.failing()["any"] | (report.min_dihedral_deg < min_dihedral_deg)
    poor_before = int(poor.sum())
    on_faces = boundary_face_counts(mesh.tets)
    caps = (poor | (report.min_dihedral_deg < cap_dihedral_deg)) & (on_faces >= 2)
    # a poor element with one face on the surface: removing it exposes its three other faces,
    # which lie close to the one removed (a flat element); not where an edge from its fourth
    # node already runs along the surface (the surface would fold onto that edge)
    peel = poor & (on_faces == 1)
    peel[peel] = _apex_edges_inside(mesh.tets, np.flatnonzero(peel))
    tets = mesh.tets[~(caps | peel)]
    poor = poor[~(caps | peel)]
    tets, poor, collapsed = _collapse_short_edges(nodes, tets, poor, min_dihedral_deg)
    incidence = csr_matrix((np.ones(tets.size), (tets.ravel(), np.repeat(np.arange(len(tets)), 4))),
                           shape=(len(nodes), len(tets)))
    on_boundary = boundary_nodes(tets, len(nodes))
    faces = boundary_faces(tets)[0]
    smooth = poor | _interior_slivers(tets, mesh_quality(TetMesh(nodes, tets)), sliver_dihedral_deg)
    poor_tets = {tuple(tet) for tet in tets[smooth]}
    moved = 0
    for node in np.unique(tets[smooth]):
        around = tets[incidence.indices[incidence.indptr[node]:incidence.indptr[node + 1]]]
        if on_boundary[node]:
            # along the surface only: halfway at most to the mean of its surface neighbours, which
            # spreads a short boundary edge and moves the skin by a fraction of a millimetre
            ring = np.setdiff1d(np.unique(faces[(faces == node).any(axis=1)]), [node])
            targets, weights = [nodes[ring].mean(axis=0)], (0.25, 0.5)
        else:
            targets = [nodes[np.setdiff1d(np.unique(around), [node])].mean(axis=0)]
            targets += [_ideal_apex(nodes, tet, node) for tet in around if tuple(tet) in poor_tets]
            weights = (0.25, 0.5, 0.75, 1.0)
        old = nodes[node].copy()
        trials = np.array([old] + [old + weight * (target - old) for target in targets for weight in weights])
        scores = _scores_at(nodes, around, node, trials, min_dihedral_deg)
        best = int(np.argmax(scores))  # the first of the best, as trying them in turn finds it
        if scores[best] > scores[0]:
            nodes[node] = trials[best]
            moved += 1
    used = np.zeros(len(nodes), bool)
    used[tets.ravel()] = True
    remap = np.cumsum(used) - 1
    return TetMesh(nodes[used], remap[tets]), {"caps_removed": int(caps.sum()), "peeled": int(peel.sum()),
                                               "edges_collapsed": collapsed, "nodes_moved": moved,
                                               "poor_before": poor_before}


SHORT_EDGE_RATIO = 0.2  # an element's edge this much shorter than its longest is collapsed
FLAT_CORNER_DEG = 150.0  # a face corner wider than this (the seed's criterion) marks a flat face
_PAIRS_ORDER = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
_PAIRS = {frozenset(pair): k for k, pair in enumerate(_PAIRS_ORDER)}


def _edges_to_collapse(nodes: np.ndarray, tets: np.ndarray, poor: np.ndarray) -> np.ndarray:
    """For each element, the edge (0-5, in the order (0,1) (0,2) (0,3) (1,2) (1,3) (2,3)) whose
    collapse would repair it, or -1: of a poor needle (an edge under ``SHORT_EDGE_RATIO`` of its
    longest) that shortest edge; of a poor element with a face corner wider than
    ``FLAT_CORNER_DEG`` (a node lying almost on the opposite edge of a face, where moving nodes
    along the surface does not reach) the shorter of the two edges at that corner."""
    p = nodes[tets]
    lengths = np.stack([np.linalg.norm(p[:, i] - p[:, j], axis=1) for i, j in _PAIRS_ORDER], axis=1)
    chosen = np.full(len(tets), -1)
    needle = poor & (lengths.min(axis=1) < SHORT_EDGE_RATIO * lengths.max(axis=1))
    chosen[needle] = lengths[needle].argmin(axis=1)
    for element in np.flatnonzero(poor & ~needle):
        widest, edge = FLAT_CORNER_DEG, -1
        for corner in range(4):
            others = [k for k in range(4) if k != corner]
            for a, b in ((others[0], others[1]), (others[0], others[2]), (others[1], others[2])):
                u, v = p[element, a] - p[element, corner], p[element, b] - p[element, corner]
                angle = np.degrees(np.arccos(np.clip(u @ v / (np.linalg.norm(u) * np.linalg.norm(v)), -1.0, 1.0)))
                if angle > widest:
                    shorter = a if np.linalg.norm(u) < np.linalg.norm(v) else b
                    widest, edge = angle, _PAIRS[frozenset((corner, shorter))]
        chosen[element] = edge
    return chosen


def _collapse_short_edges(nodes: np.ndarray, tets: np.ndarray, poor: np.ndarray,
                          min_dihedral_deg: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Collapse the edge :func:`_edges_to_collapse` chooses of each poor element (of a needle,
    two surface or interface points 1 mm apart among 15-20 mm edges, its shortest edge; of an
    element with a flat face, an edge at the face's widest corner), which no node move repairs:
    its two nodes become one (at the boundary node's place if one is on the boundary, else at the
    midpoint; two boundary nodes only along a surface edge that passes the link condition, never
    across the volume, which would pinch the surface, and at the midpoint or at the end that
    leaves the elements around best), the elements holding both are removed, and the change is
    kept only if every element around is positive and they rank better than before
    (:func:`_rank`: fewer poor elements, or as many and a better worst one).
    ``nodes`` is updated in place; returns the elements, their poor flags and the number of edges
    collapsed."""
    pairs = _PAIRS_ORDER
    chosen = _edges_to_collapse(nodes, tets, poor)
    candidates = np.flatnonzero(chosen >= 0)
    if len(candidates) == 0:
        return tets, poor, 0
    original, original_tets = nodes.copy(), tets
    tets = tets.copy()
    on_boundary = boundary_nodes(tets, len(nodes))
    ring: dict[int, set[int]] = {}  # surface neighbours of each boundary node
    for face in boundary_faces(tets)[0]:
        for a in face:
            ring.setdefault(int(a), set()).update(int(b) for b in face if b != a)
    alive = np.ones(len(tets), bool)
    touched = np.zeros(len(nodes), bool)
    holding: dict[int, set[int]] = {}
    for element, tet in enumerate(tets):
        for node in tet:
            holding.setdefault(int(node), set()).add(element)
    collapsed = 0
    for element in candidates:
        if not alive[element]:
            continue
        i, j = pairs[int(chosen[element])]
        keep, drop = int(tets[element, i]), int(tets[element, j])
        if touched[keep] or touched[drop]:
            continue
        if on_boundary[keep] and on_boundary[drop]:
            # a surface edge whose ends share exactly the two surface neighbours of its two
            # triangles (the link condition): collapsing it keeps the surface a manifold
            if drop not in ring[keep] or len(ring[keep] & ring[drop]) != 2:
                continue
            # at the midpoint or at either end, whichever leaves the elements around best
            places = [0.5 * (nodes[keep] + nodes[drop]), nodes[keep].copy(), nodes[drop].copy()]
        else:
            if on_boundary[drop]:
                keep, drop = drop, keep
            places = [nodes[keep].copy() if on_boundary[keep] else 0.5 * (nodes[keep] + nodes[drop])]
        around = sorted(e for e in holding[keep] | holding[drop] if alive[e])
        both = [e for e in around if keep in tets[e] and drop in tets[e]]
        rest = [e for e in around if e not in both]
        best_score = _rank(nodes, tets[around], min_dihedral_deg)
        trial = tets[rest].copy()
        trial[trial == drop] = keep
        saved, best = nodes[keep].copy(), None
        for place in places:
            nodes[keep] = place
            score = _rank(nodes, trial, min_dihedral_deg)
            if score > best_score:
                best, best_score = place, score
        nodes[keep] = saved if best is None else best
        if best is None:
            continue
        tets[rest] = trial
        alive[both] = False
        holding[keep] |= set(rest)
        touched[[keep, drop]] = True
        if on_boundary[drop]:
            for node in ring.pop(drop):
                ring[node].discard(drop)
                if node != keep:
                    ring[node].add(keep)
                    ring[keep].add(node)
            ring[keep].discard(drop)
        collapsed += 1
    if collapsed and not _conforming(tets[alive]):  # a collapse the local checks missed: undo them all
        nodes[:] = original
        return original_tets, poor, 0
    return tets[alive], poor[alive], collapsed


def _conforming(tets: np.ndarray) -> bool:
    """Whether every face is shared by at most two elements and no element repeats another."""
    faces = np.sort(tets[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3), axis=1)
    _, counts = unique_rows(faces, return_counts=True)
    return bool(counts.max() <= 2) and len(unique_rows(np.sort(tets, axis=1))) == len(tets)
