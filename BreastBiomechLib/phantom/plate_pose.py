"""A phantom truth's plate turned about a pivot of its own: the rig's paddle mounted a little off,
turning about its mount rather than about the point its plane is recorded at.

This is the hidden truth's implementation, kept apart from the discrepancy workflow's plate
candidate (:mod:`BreastBiomechLib.discrepancy.effects.plate_tilt`, which turns a plate about its
final point with :func:`~BreastBiomechLib.solver.placement.posed_plate` and moves it along its
normal): a truth made by the candidate's own code would test the candidate against itself
(issue 77, point 5). Both name the angles by the same two tilt axes
(:func:`~BreastBiomechLib.solver.placement.tilt_axes`), the vocabulary of a plate's pose.
Positions in LPS mm, angles in degrees.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from BreastBiomechLib.solver.model import Plate, PlateEdge
from BreastBiomechLib.solver.placement import tilt_axes

HELD_TOLERANCE_MM = 1e-6  # a plate whose travel along its normal is below this is a held one


def turned_plate(plate: Plate, nodes_mm: np.ndarray, tilt_deg, pivot_mm=(0.0, 0.0, 0.0)) -> Plate:
    """``plate`` with its final pose turned rigidly by ``tilt_deg`` (about its first tilt axis,
    then its second) about a pivot at ``pivot_mm`` from its final point (``point + displacement``)
    in the plate's own frame: along the first tilt axis, the second, and the normal (< 0 behind
    the plate, where a paddle's mount is). The turned plate starts where it just touches the
    first of its contact nodes (``slave_nodes`` of ``nodes_mm``) and travels along its turned
    normal to the turned final pose; a held plate (no travel) that the turn lifts off the tissue
    stays at its turned pose without travel (the other plate pushes the breast onto it), one that
    the turn presses into the tissue travels there from touching. Raises ValueError for a moving
    plate whose turned final pose never reaches the tissue."""
    angles = np.radians(np.asarray(tilt_deg, float).reshape(-1))
    pivot = np.asarray(pivot_mm, float).reshape(-1)
    if angles.shape != (2,) or pivot.shape != (3,) or not np.all(np.isfinite(np.r_[angles, pivot])):
        raise ValueError(f"plate {plate.name!r}: a turn is two finite angles (degrees) about a pivot of three finite "
                         f"coordinates (mm), not {tilt_deg!r} about {pivot_mm!r}")
    first, second = tilt_axes(plate)
    turn = (Rotation.from_rotvec(angles[1] * second) * Rotation.from_rotvec(angles[0] * first)).as_matrix()
    final = plate.point + plate.displacement
    centre = final + pivot[0] * first + pivot[1] * second + pivot[2] * plate.normal
    turned_final = centre + turn @ (final - centre)
    normal = turn @ plate.normal
    along = float(plate.displacement @ plate.normal)
    in_plane = turn @ (plate.displacement - along * plate.normal)
    edge = None if plate.edge is None else PlateEdge(turn @ plate.edge.direction, plate.edge.distance, plate.edge.radius)
    contacts = np.asarray(nodes_mm, float)[plate.slave_nodes]

    def posed(travel: float) -> Plate:  # the plate ``travel`` back along its normal from the turned final pose
        return Plate(turned_final - in_plane - travel * normal, normal, np.zeros(3), [], plate.name, edge, plate.friction)

    gaps = posed(0.0).gaps(contacts)
    gaps = gaps[np.isfinite(gaps)]
    if len(gaps) == 0:
        raise ValueError(f"plate {plate.name!r}: turned so, none of its contact nodes is within its reach")
    travel = -float(gaps.min())
    if travel < 0:
        if abs(along) > HELD_TOLERANCE_MM:
            raise ValueError(f"plate {plate.name!r}: turned so, it ends {-travel:.2f} mm short of the tissue and would "
                             "never touch it; a smaller turn or a pivot nearer the plate")
        travel = 0.0
    for _ in range(100):  # a rounded edge moved back clears its nodes by less than the move
        inside = -float(posed(travel).gaps(contacts).min())
        if inside <= 1e-9:
            break
        travel += inside
    return Plate(turned_final - in_plane - travel * normal, normal, travel * normal + in_plane, plate.slave_nodes,
                 plate.name, edge, plate.friction)
