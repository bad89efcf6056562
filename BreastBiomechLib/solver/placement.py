"""Placing compression plates on a mesh: two rigid plates tangent to the breast on opposite sides
along an axis, closing by a given fraction of the breast's thickness between them (the seed's
medio-lateral compression). Positions in the mesh's frame (LPS mm)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from BreastBiomechLib.mesh.tetmesh import TetMesh, boundary_nodes
from BreastBiomechLib.solver.model import PENETRATION_TOLERANCE_MM, Plate, PlateEdge

AXES = {"LR": (1.0, 0.0, 0.0), "AP": (0.0, 1.0, 0.0), "SI": (0.0, 0.0, 1.0)}  # LPS x, y, z
MOVING = ("both", "first", "second")
PLATE_SIDES = {"LR": ("right", "left"), "AP": ("anterior", "posterior"), "SI": ("inferior", "superior")}
TOUCH_TOLERANCE_MM = 1e-6  # a plate this close to the tissue touches it
# the sides of the first and second plate of each axis: the first is at the lower LPS coordinate
# (BreastSimulation's plate names say the same; that module file does not import the solver)


def axis_vector(axis) -> np.ndarray:
    """Unit vector (LPS) of an axis name ("LR", "AP", "SI") or of a given 3-vector."""
    if isinstance(axis, str):
        try:
            return np.array(AXES[axis.upper()])
        except KeyError:
            raise ValueError(f"unknown compression axis {axis!r}; use one of {list(AXES)} or a 3-vector") from None
    vector = np.asarray(axis, float).reshape(3)
    norm = np.linalg.norm(vector)
    if norm == 0:
        raise ValueError("the compression axis must not be the zero vector")
    return vector / norm


def nodes_in_front(nodes_mm: np.ndarray, candidates, plates: list[Plate]) -> np.ndarray:
    """The ``candidates`` (node ids) that start on the tissue side of every plate (within the
    round-off tolerance): the nodes the plates can touch. A plate is a plane, so skin that
    starts behind it - the chest's skin beside the breast when the plates are placed against the
    breast - is not its contact: it is where the real, finite plate does not reach."""
    candidates = np.asarray(candidates, dtype=np.int64).ravel()
    keep = np.ones(len(candidates), bool)
    for plate in plates:
        keep &= plate.gaps(nodes_mm[candidates]) >= -PENETRATION_TOLERANCE_MM
    return candidates[keep]


def within_reach(nodes_mm: np.ndarray, candidates, plates: list[Plate]) -> np.ndarray:
    """The ``candidates`` (node ids) that lie short of every edged plate's end (its flat face
    plus the rounded edge): past it the plate has ended and cannot touch them."""
    candidates = np.asarray(candidates, dtype=np.int64).ravel()
    keep = np.ones(len(candidates), bool)
    for plate in plates:
        if plate.edge is not None:
            along = (nodes_mm[candidates] - plate.point) @ plate.edge.direction
            keep &= along < plate.edge.distance + plate.edge.radius
    return candidates[keep]


def held_plates_touching(nodes_mm: np.ndarray, plates: list[Plate], contacts) -> list[Plate]:
    """``plates`` with each held one (no displacement) moved along its normal until it touches the
    nearest of its ``contacts`` (node ids): a held plate placed against the breast's widest
    point, where that lies in the band by the chest that plates do not touch, would otherwise
    stand off the tissue it is meant to hold, and the moving plate would push the breast over
    instead of pressing it against the held one. Moving plates are returned as they are."""
    contacts = np.asarray(contacts, dtype=np.int64).ravel()
    placed = []
    for plate in plates:
        if np.any(plate.displacement) or len(contacts) == 0:
            placed.append(plate)
            continue
        points = nodes_mm[contacts]
        for _ in range(50):  # a node facing the rounded edge closes by less than the plate moves
            gap = float(plate.gaps(points).min())
            if gap <= TOUCH_TOLERANCE_MM:
                break
            plate = replace(plate, point=plate.point + gap * plate.normal)
        placed.append(plate)
    return placed


def final_planes(plates: list[Plate]) -> list[dict]:
    """Where ``plates`` end (what a compressed image shows, and plates.json holds): name, final
    ``point`` and ``normal`` (LPS mm, towards the tissue), the travel along the normal (mm) and
    the rounded edge. A plate moves along its normal, so its edge's distance holds. The inverse
    of :func:`plates_to_final_planes`."""
    return [{"name": p.name, "point": (p.point + p.displacement).tolist(), "normal": p.normal.tolist(),
             "travel_mm": float(p.displacement @ p.normal), **({"edge": p.edge.to_dict()} if p.edge else {})}
            for p in plates]


def plates_to_final_planes(mesh: TetMesh, planes: list[dict], candidates, extent_nodes=None) -> list[Plate]:
    """Plates that start touching the mesh (its ``extent_nodes``, e.g. the breast skin) and end
    on measured final ``planes`` (dicts: ``name``, ``point`` and ``normal`` towards the tissue,
    LPS mm; optional ``edge`` as in a case file): each plate travels along its normal from the
    mesh's extreme node to its plane. The contact nodes are the ``candidates`` between the plates
    and within their reach. How a fitting mesh meets the plates seen in a compressed image."""
    reference = mesh.nodes if extent_nodes is None else mesh.nodes[np.asarray(extent_nodes, dtype=np.int64)]
    if len(reference) == 0:
        raise ValueError("the node set the plates are placed against is empty")
    plates = []
    for i, plane in enumerate(planes):
        name = plane.get("name", f"plate{i + 1}")
        normal = np.asarray(plane["normal"], float)
        normal = normal / np.linalg.norm(normal)
        final = np.asarray(plane["point"], float)
        start = float((reference @ normal).min())  # the plate starts touching the mesh here
        travel = float(final @ normal) - start
        if travel < 0:
            raise ValueError(f"plate {name!r}: its final plane lies {-travel:.1f} mm outside the mesh, so it would "
                             "never touch it; check the plates and that the mesh and the plates share a frame (LPS mm)")
        edge = plane.get("edge")
        plates.append(Plate(final - travel * normal, normal, travel * normal, [], name,
                            PlateEdge(edge["direction"], edge["distance"], edge["radius"]) if edge else None))
    contacts = nodes_in_front(mesh.nodes, within_reach(mesh.nodes, candidates, plates), plates)
    if len(contacts) == 0:
        raise ValueError("no contact node lies between the plates; check the plates and the contact nodes")
    for plate in plates:
        plate.slave_nodes = contacts
    return plates


MIN_CHEST_CLEARANCE_MM = 5.0


def plate_contacts(mesh: TetMesh, candidates, plates: list[Plate], chest_clearance_mm: float | None = None,
                   edge_radius_mm: float | None = None) -> np.ndarray:
    """The ``candidates`` (node ids) the plates touch: those that start between them
    (:func:`nodes_in_front`) and, on a mesh with a chest (muscle elements in the cell array
    ``tissue``, or a ``chest_wall`` point array), lie anterior to the plates' posterior edge.

    The plates' flat faces end ``chest_clearance_mm`` anterior to the chest's most anterior
    node (None: the larger plate travel, at least 5 mm) in a rounded edge of ``edge_radius_mm``
    (None: the larger plate travel, at least 5 mm, whatever the clearance: a tighter edge wraps
    the tissue it pushes round a sharper corner; at 8 mm clearance and 25 mm travel the 6 mm
    truth mesh of the 450 cm3 test phantom inverted 13 elements with an 8 mm edge, 1 with 25 mm)
    (:class:`~BreastBiomechLib.solver.model.PlateEdge`, set on each plate whose plane runs
    anterior-posterior). The band left free stands for the rig's support between the chest and
    the plates' posterior edge, and keeps a rigid plate from shearing the breast base against the
    stiffer chest wall; the rounded edge spreads the step between pushed and free skin over
    several elements (a knife edge inverted elements there at 40 % compression)."""
    from BreastBiomechLib.mesh.node_sets import chest_front_y

    travel = max([MIN_CHEST_CLEARANCE_MM] + [float(np.linalg.norm(p.displacement)) for p in plates])
    if chest_clearance_mm is None:
        chest_clearance_mm = travel
    if chest_clearance_mm < 0:
        raise ValueError(f"the chest clearance is a distance (mm >= 0), not {chest_clearance_mm}")
    if edge_radius_mm is None:
        edge_radius_mm = travel
    if not edge_radius_mm > 0:
        raise ValueError(f"the plates' edge radius must be positive (mm), not {edge_radius_mm}")
    candidates = np.asarray(candidates, dtype=np.int64).ravel()
    tissue = mesh.cell_data.get("tissue")
    chest = mesh.point_data.get("chest_wall")
    front = chest_front_y(mesh, np.zeros(len(mesh.tets), int) if tissue is None else np.asarray(tissue).astype(int),
                          np.zeros(len(mesh.nodes), bool) if chest is None else np.asarray(chest) > 0)
    if front is not None:
        end = front - chest_clearance_mm  # LPS y where the plates' flat faces end
        for plate in plates:
            posterior = np.array([0.0, 1.0, 0.0]) - plate.normal[1] * plate.normal  # +y in the plate's plane
            if np.linalg.norm(posterior) > 0.5:
                direction = posterior / np.linalg.norm(posterior)
                plate.edge = PlateEdge(direction, (end - plate.point[1]) / direction[1], edge_radius_mm)
            else:  # a plate facing the chest: no edge, the band is left out of its contact
                candidates = candidates[mesh.nodes[candidates, 1] < end]
    contacts = nodes_in_front(mesh.nodes, within_reach(mesh.nodes, candidates, plates), plates)
    if len(contacts) == 0:
        raise ValueError(f"no contact node lies between the plates and more than {chest_clearance_mm:g} mm anterior "
                         "to the chest wall; check the plates and the contact nodes, or lower the chest clearance")
    return contacts


def compression_plates(mesh: TetMesh, axis="LR", compression: float = 0.25, slave_nodes=None,
                       names: tuple[str, str] = ("plate1", "plate2"), moving: str = "both",
                       extent_nodes=None) -> list[Plate]:
    """Two plates normal to ``axis`` touching the mesh (or the ``extent_nodes``, e.g. the breast
    skin of a mesh that also holds the chest) at its lowest and highest extent along it
    (the first plate's normal is +axis, the second's -axis, both towards the tissue), which close
    the gap between them by ``compression`` (a fraction in (0, 1)) of the thickness: half each
    (``moving="both"``), or all by the first or second plate with the other held (the seed's fixed
    and movable plates). The contact nodes are the ``slave_nodes`` (default: every boundary node
    of the mesh) that start between the plates (:func:`nodes_in_front`). Each plate's ``point``
    is the mesh centre projected onto it, so a drawn plate is centred on the breast."""
    if not 0.0 < compression < 1.0:
        raise ValueError(f"compression must be a fraction of the thickness in (0, 1), not {compression}")
    if moving not in MOVING:
        raise ValueError(f"moving must be one of {MOVING}, not {moving!r}")
    if len(mesh.nodes) == 0:
        raise ValueError("the mesh has no nodes")
    direction = axis_vector(axis)
    if slave_nodes is None:
        slave_nodes = np.flatnonzero(boundary_nodes(mesh.tets, len(mesh.nodes)))
    reference = mesh.nodes if extent_nodes is None else mesh.nodes[np.asarray(extent_nodes, dtype=np.int64)]
    if len(reference) == 0:
        raise ValueError("the node set the plates are placed against is empty")
    along = reference @ direction
    lo, hi = float(along.min()), float(along.max())
    centre = reference.mean(axis=0)
    centre = centre - (centre @ direction) * direction
    travel = compression * (hi - lo)
    share = {"both": (0.5, 0.5), "first": (1.0, 0.0), "second": (0.0, 1.0)}[moving]
    plates = [Plate(centre + lo * direction, direction, share[0] * travel * direction, slave_nodes, names[0]),
              Plate(centre + hi * direction, -direction, -share[1] * travel * direction, slave_nodes, names[1])]
    between = nodes_in_front(mesh.nodes, slave_nodes, plates)
    if len(between) == 0:
        raise ValueError("no contact node lies between the plates; check the contact node set")
    for plate in plates:
        plate.slave_nodes = between
    return plates


MAX_TILT_DEG = 10.0  # paddles tilt 0.04-0.7 deg; larger is a wrong sign or unit, not a pose
MAX_OFFSET_MM = 10.0  # plates read off an image are out by a voxel or two; larger is a wrong unit or frame


def tilt_axes(plate: Plate) -> tuple[np.ndarray, np.ndarray]:
    """The two in-plane axes (unit, LPS) a plate's tilt angles turn it about: the first along its
    edge direction (towards where its flat face ends, e.g. the chest) or, for a plate without an
    edge, the in-plane part of LPS +y (posterior; +z, superior, for a plate facing y); the second
    is normal x first. With a medio-lateral plate ending at the chest the first angle tilts it
    superior-inferiorly, the second anterior-posteriorly (the nipple end closing more or less)."""
    if plate.edge is not None:
        first = plate.edge.direction
    else:
        axis = np.array([0.0, 1.0, 0.0]) if abs(plate.normal[1]) < np.sqrt(0.5) else np.array([0.0, 0.0, 1.0])
        first = axis - (axis @ plate.normal) * plate.normal
        first = first / np.linalg.norm(first)
    return first, np.cross(plate.normal, first)


def _rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Right-handed rotation matrix about the unit ``axis``."""
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1.0 - np.cos(angle_rad)) * (k @ k)


def _reaches_tissue(plate: Plate, contacts: np.ndarray) -> bool:
    """Whether ``plate`` in its final pose (``point + displacement``) reaches the undeformed
    ``contacts`` (N, 3) mm, to :data:`TOUCH_TOLERANCE_MM`: touching them (a held plate, onto
    which the other plate pushes the breast) or pressed into them (a moving plate)."""
    gaps = Plate(plate.point + plate.displacement, plate.normal, np.zeros(3), [], plate.name, plate.edge).gaps(contacts)
    gaps = gaps[np.isfinite(gaps)]
    return len(gaps) > 0 and float(gaps.min()) <= TOUCH_TOLERANCE_MM


def posed_plate(plate: Plate, nodes_mm: np.ndarray, tilt_deg=(0.0, 0.0), offset_mm: float = 0.0) -> Plate:
    """``plate`` with its final pose changed: turned by ``tilt_deg`` (two angles, degrees, about
    :func:`tilt_axes`, right-handed) about its final point (``point + displacement``) and moved
    ``offset_mm`` along its new normal (> 0: further into the tissue). It starts where it just
    touches the first of its contact nodes (``slave_nodes`` of the mesh nodes ``nodes_mm``, LPS
    mm) and travels along its new normal to the final pose (plus the turned in-plane part of
    its old travel, if any). A plate whose final pose reached the undeformed tissue (touching it, or
    pressed into it) and that the turn or an offset away from the tissue (< 0) lifts off it ends
    at its new final pose without travel: the other plate pushes the breast onto it. A plate
    whose recorded final pose already stood off the tissue (another frame) is refused.
    Edge, friction, name and contact nodes are kept (the edge turned with the plate). The pose a fit or a hidden-effect phantom gives a plate: paddles tilt by
    0.04-0.7 degrees."""
    tilt = np.asarray(tilt_deg, float).reshape(-1)
    if tilt.shape != (2,) or not np.all(np.isfinite(tilt)) or not np.isfinite(offset_mm):
        raise ValueError(f"plate {plate.name!r}: the tilt is two finite angles (degrees) and the offset a finite "
                         f"distance (mm), not {tilt_deg!r} and {offset_mm!r}")
    if np.any(np.abs(tilt) > MAX_TILT_DEG):
        raise ValueError(f"plate {plate.name!r}: a tilt of {np.abs(tilt).max():g} degrees is more than "
                         f"{MAX_TILT_DEG:g}; paddles tilt by under a degree - check the unit (degrees) and sign")
    if abs(offset_mm) > MAX_OFFSET_MM:
        raise ValueError(f"plate {plate.name!r}: an offset of {abs(offset_mm):g} mm is more than {MAX_OFFSET_MM:g}; "
                         "a plate read off an image is out by a voxel or two - check the unit (mm) and the frame")
    first, second = tilt_axes(plate)
    turn = _rotation(second, np.radians(tilt[1])) @ _rotation(first, np.radians(tilt[0]))
    normal = turn @ plate.normal
    along = plate.displacement @ plate.normal
    in_plane = turn @ (plate.displacement - along * plate.normal)
    final = plate.point + plate.displacement + offset_mm * normal
    edge = None
    if plate.edge is not None:
        from BreastBiomechLib.solver.model import PlateEdge

        edge = PlateEdge(turn @ plate.edge.direction, plate.edge.distance, plate.edge.radius)
    contacts = np.asarray(nodes_mm, float)[plate.slave_nodes]
    at_end = Plate(final - in_plane, normal, np.zeros(3), [], plate.name, edge, plate.friction)
    gaps = at_end.gaps(contacts)
    gaps = gaps[np.isfinite(gaps)]
    if len(gaps) == 0:
        raise ValueError(f"plate {plate.name!r}: none of its contact nodes is within its reach")
    travel = -float(gaps.min())
    if -TOUCH_TOLERANCE_MM <= travel < 0:  # a held plate placed onto the tissue, to rounding
        travel = 0.0
    if travel < 0 and _reaches_tissue(plate, contacts):
        # a plate that reached the undeformed tissue (a held one touching it, or one pressed a
        # little into it, as a fitting mesh's held plate is) and that the pose change lifted off
        # it (turned about its final point, its rounded edge with it, or moved away along its
        # normal: a candidate's secant, a refit): it ends there without travel, and the other
        # plate pushes the breast onto it. Its stand-off is the pose change's own.
        travel = 0.0
    if travel < 0:
        raise ValueError(f"plate {plate.name!r}: in that pose it ends {-travel:.2f} mm short of the tissue and would "
                         "never touch it; lower the offset or check the tilt")
    # moved back along its normal, a rounded edge clears the nodes on it by less than the move:
    # back off until none starts inside (the fillet's distance grows with the move, at most as fast)
    for _ in range(100):
        start = Plate(final - in_plane - travel * normal, normal, np.zeros(3), [], plate.name, edge, plate.friction)
        inside = -float(start.gaps(contacts).min())
        if inside <= 1e-9:
            break
        travel += inside
    return Plate(final - in_plane - travel * normal, normal, travel * normal + in_plane, plate.slave_nodes,
                 plate.name, edge, plate.friction)
