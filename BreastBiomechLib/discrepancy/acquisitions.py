"""The acquisitions a design may recommend (:mod:`BreastBiomechLib.discrepancy.design`): further
scans of the same breast on the fitted case's two-plate rig, each as its final plate planes on the
fitting mesh - the plates closing 10 or 20 % of the breast's thickness further or less, all of the
closure by one plate, or the same closure along the other axis (LR and SI swapped); and, where a
one-plate push does not solve at this fit (an element inverted on the way: the breast pushed
sideways against its chest wall by the whole closure), the same plate alone closing half as far
(:func:`half_push`).

Frames and units: LPS millimetres, the imaged (undeformed) frame.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

KINDS = ("compression", "one-plate", "rotated")  # the library's acquisitions, by kind
COMPRESSION_CHANGES = (-0.2, -0.1, 0.1, 0.2)  # of the breast's thickness between the plates at the start
MOST_COMPRESSION = 0.7  # a closure beyond this fraction of the thickness is not an acquisition made
ONE_PLATE_SHARE = 0.95  # a plate with this share of the closure or more is the one that moved
HALF = "-half"  # the suffix of a one-plate push made half as far (:func:`half_push`)
SWAPPED_AXES = {0: "SI", 1: "LR", 2: "LR"}  # the rotated acquisition's axis, by the plates' present axis (L, P, S)


@dataclass(frozen=True)
class Acquisition:
    """A further scan: its ``name`` (a state name), ``description`` (words for the report),
    final plate ``planes`` (dicts as in a case's plates.json: ``name``, ``point``, ``normal``
    towards the tissue, optional ``edge``; LPS mm, the imaged frame) and ``kind`` (of
    :data:`KINDS`)."""

    name: str
    description: str
    planes: tuple[dict, ...]
    kind: str = ""


def acquisition_library(fitted, state=None, kinds=KINDS) -> list[Acquisition]:
    """The acquisitions of ``kinds`` (or named: an entry of ``kinds`` may be an acquisition's
    name, e.g. "only-left") for the fitted case's two-plate rig, from its first
    state's plates at fit parameters ``z`` (default the fit's): the closure changed by each of
    :data:`COMPRESSION_CHANGES` of the thickness (shared between the plates as now), all of it
    by one plate (each plate not already moving alone), and the same closure along the other
    axis (LR becomes SI, SI and AP become LR; plates touching the breast skin, ending where the
    present plates end: :func:`_edge_kept`); a one-plate push half as far
    (``only-<plate>-half``, :func:`half_push`) where asked for by name.
    Refuses a rig of other than two facing plates, and a kind or name the library does not
    have for this rig."""
    from BreastBiomechLib.solver.placement import compression_plates

    plates, travel, closure, thickness = _rig(fitted, state)
    shares = travel / closure
    out = []
    for change in COMPRESSION_CHANGES:
        now = closure + change * thickness
        if 0 < now < MOST_COMPRESSION * thickness:
            out.append(Acquisition(f"compression{100 * change:+.0f}",
                                   f"compress again {abs(100 * change):.0f} % of the breast's thickness "
                                   f"{'further' if change > 0 else 'less'} ({100 * now / thickness:.0f} % in all)",
                                   _planes(plates, travel * now / closure), "compression"))
    for k, plate in enumerate(plates):
        if shares[k] < ONE_PLATE_SHARE:
            out.append(_one_plate(plates, k, closure, thickness))
            if f"only-{plate.name}{HALF}" in kinds:  # asked for by name only
                out.append(_one_plate(plates, k, closure, thickness, half=True))
    axis = SWAPPED_AXES[int(np.argmax(np.abs(plates[0].normal)))]
    moving = "both" if shares.max() < ONE_PLATE_SHARE else ("first" if shares[0] > shares[1] else "second")
    turned = compression_plates(fitted.mesh, axis, closure / thickness, names=(f"{axis}-1", f"{axis}-2"),
                                moving=moving, extent_nodes=fitted.mesh.node_set("breast_skin"))
    turned = [replace(new, edge=_edge_kept(old, new)) for old, new in zip(plates, turned)]
    out.append(Acquisition(f"rotated-{axis}", f"compress as far along {axis} instead (the plates turned 90 degrees)",
                           tuple(_plane(p, p.point + p.displacement) for p in turned), "rotated"))
    wanted = set(kinds)
    unknown = sorted(wanted - set(KINDS) - {a.name for a in out})
    if unknown:
        raise ValueError(f"unknown acquisitions {unknown}: give kinds ({', '.join(KINDS)}) or names of this case's "
                         f"({', '.join(a.name for a in out)})")
    out = [a for a in out if a.kind in wanted or a.name in wanted]
    return out


def half_push(fitted, state, acquisition: Acquisition) -> Acquisition | None:
    """The one-plate ``acquisition`` of :func:`acquisition_library` made half as far: the same
    plate alone closing half the present closure (``only-<plate>-half``), the push a design
    simulates where the whole one does not solve at the fit ``state`` (default the fit's); None
    for an acquisition of another kind or one halved already."""
    if acquisition.kind != "one-plate" or acquisition.name.endswith(HALF):
        return None
    plates, _, closure, thickness = _rig(fitted, state)
    k = [p.name for p in plates].index(acquisition.name[len("only-"):])
    return _one_plate(plates, k, closure, thickness, half=True)


def _rig(fitted, state):
    """The fitted case's two facing plates at the model ``state`` (default the fit's), each
    plate's travel towards the tissue (mm), their closure (mm) and the breast's thickness
    between them at rest (mm). Refuses another rig, or plates that do not compress."""
    from BreastBiomechLib.discrepancy.state import ModelState

    plates = (state or ModelState(fitted, fitted.z)).variant().plates
    if len(plates) != 2 or plates[0].normal @ plates[1].normal > -0.99:
        raise ValueError(f"{fitted.case_dir}: the acquisition library is made for two facing plates; this case has "
                         f"{len(plates)} plate(s){'' if len(plates) != 2 else ' that do not face each other'}")
    travel = np.array([max(float(p.displacement @ p.normal), 0.0) for p in plates])
    closure = float(travel.sum())
    thickness = float((plates[1].point - plates[0].point) @ plates[0].normal)
    if not (closure > 0 and thickness > closure):
        raise ValueError(f"{fitted.case_dir}: the plates close {closure:.1f} mm of a {thickness:.1f} mm breast; a "
                         "compression is needed to design the next one")
    return plates, travel, closure, thickness


def _planes(plates, travels) -> tuple[dict, ...]:
    """The final planes of ``plates`` each moved its travel (mm) towards the tissue. Where the
    larger travel exceeds the measured scan's, plates that end before the chest (a rounded edge)
    end as much further from it and round as much more (:func:`_grown`): the rule by which the
    library places plates for any closure (:func:`~BreastBiomechLib.solver.placement.plate_contacts`:
    the flat faces end the larger travel anterior to the chest, rounded by as much), applied to
    the measured plates. The measured scan's edges kept for a longer push wrap the pushed tissue
    round a corner too sharp for a fitting mesh: one plate pushing the whole closure so inverted
    elements of every fitting mesh of the two-state suite's chest-wall cases (2026-12-07). A real
    rig's plates do not change with the travel: the edges model the support band the library's
    way, not a given rig's."""
    grow = max(0.0, float(np.max(travels)) - max(float(p.displacement @ p.normal) for p in plates))
    return tuple(_plane(replace(p, edge=_grown(p.edge, grow)), p.point + t * p.normal) for p, t in zip(plates, travels))


def _grown(edge, grow_mm: float):
    """``edge`` (:class:`~BreastBiomechLib.solver.model.PlateEdge`, or None: unbounded) ending
    ``grow_mm`` further from the chest (its direction points towards it) with a radius that
    much larger."""
    from BreastBiomechLib.solver.model import PlateEdge

    if edge is None or grow_mm == 0:
        return edge
    return PlateEdge(edge.direction, edge.distance - grow_mm, edge.radius + grow_mm)


def _one_plate(plates, k: int, closure: float, thickness: float, half: bool = False) -> Acquisition:
    """Plate ``k`` of the two alone closing the present ``closure`` (mm; the other at rest):
    ``only-<plate>``, or half as far ``only-<plate>-half``. ``thickness``: the breast's between the
    plates at rest (mm)."""
    name, travel = plates[k].name, closure / 2 if half else closure
    planes = _planes(plates, np.where(np.arange(2) == k, travel, 0.0))
    if not half:
        return Acquisition(f"only-{name}", f"compress again as far with only the {name} plate moving", planes,
                           "one-plate")
    return Acquisition(f"only-{name}{HALF}", f"compress again with only the {name} plate moving, half as far "
                       f"({100 * travel / thickness:.0f} % of the breast's thickness)", planes, "one-plate")


def _edge_kept(plate, turned):
    """The rounded edge of ``turned`` (a plate turned about the breast from ``plate``) where
    ``plate``'s is, when that edge's direction lies in the turned plate's plane too (a plate
    that ends before the chest wall still does, turned about the anterior-posterior axis);
    None (unbounded) otherwise."""
    from BreastBiomechLib.solver.model import PlateEdge

    edge = plate.edge
    if edge is None or abs(edge.direction @ turned.normal) > 1e-6:
        return None
    at = plate.point @ edge.direction + edge.distance  # where the flat face ends, along the direction
    return PlateEdge(edge.direction, at - turned.point @ edge.direction, edge.radius)


def _plane(plate, final_point: np.ndarray) -> dict:
    """``plate``'s final plane at ``final_point`` (LPS mm) as plates.json has it."""
    return {"name": plate.name, "point": np.asarray(final_point, float).tolist(), "normal": plate.normal.tolist(),
            **({"edge": plate.edge.to_dict()} if plate.edge is not None else {})}
