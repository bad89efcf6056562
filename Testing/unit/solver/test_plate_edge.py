"""Plates that end in a rounded edge: the gap function, the contact kernel, case files, and the
plates placed on a breast mesh."""

from __future__ import annotations

import json

import numpy as np
import pytest

from BreastBiomechLib.mesh.primitives import box_mesh
from BreastBiomechLib.solver import Constraint, ElementMaterials, Loading, Material, Model, Plate, solve
from BreastBiomechLib.solver.model import PlateEdge

SIDE = 10.0  # mm
PUSH = 2.0  # mm


def _edged_plate(distance, radius=4.0, slaves=()):
    """The top plate of a SIDE-mm cube (normal -z), pushing PUSH mm down; its flat face ends
    ``distance`` mm along +x from x = 0 in a fillet of ``radius`` mm."""
    return Plate([0, 0, SIDE], [0, 0, -1], [0, 0, -PUSH], slaves, "top",
                 PlateEdge([1, 0, 0], distance, radius) if distance is not None else None)


def test_gaps_are_distances_to_the_flat_face_and_to_the_rounded_edge():
    plate = _edged_plate(5.0)
    # under the flat face: the distance below it; past the edge: to the fillet circle, whose
    # centre is 4 mm behind the face above x = 5; past the fillet's quarter: clear
    points = np.array([[2.0, 0, 9.0], [2.0, 0, 10.5], [7.0, 0, 9.0], [7.0, 0, 10.5], [5.0 + 4.0, 0, 9.9],
                       [6.0, 0, 15.0]])
    expected = [1.0, -0.5, np.hypot(2.0, 5.0) - 4.0, np.hypot(2.0, 3.5) - 4.0, np.hypot(4.0, 4.1) - 4.0, np.inf]
    np.testing.assert_allclose(plate.gaps(points), expected)
    assert _edged_plate(None).gaps(points[:1]) == pytest.approx([1.0])


def test_bad_edges_are_refused():
    with pytest.raises(ValueError, match="radius must be positive"):
        PlateEdge([1, 0, 0], 5.0, 0.0)
    with pytest.raises(ValueError, match="non-zero"):
        PlateEdge([0, 0, 0], 5.0, 1.0)
    with pytest.raises(ValueError, match="plate's plane"):
        Plate([0, 0, 0], [0, 0, 1], [0, 0, 0], [], "p", PlateEdge([1, 0, 1], 5.0, 1.0))


def _pressed_block(distance):
    """A SIDE-mm cube on a fixed frictionless floor (symmetry planes x = 0 and y = 0), its top
    face pushed down PUSH mm by :func:`_edged_plate`; returns the mesh, model and solution."""
    from BreastBiomechLib.solver import DynamicRelaxation

    mesh = box_mesh((SIDE, SIDE, SIDE), (8, 8, 8))
    top = np.flatnonzero(mesh.point_data["face_zhi"])
    constraints = [Constraint.fixed(np.flatnonzero(mesh.point_data["face_xlo"]), (True, False, False)),
                   Constraint.fixed(np.flatnonzero(mesh.point_data["face_ylo"]), (False, True, False)),
                   Constraint.fixed(np.flatnonzero(mesh.point_data["face_zlo"]), (False, False, True))]
    model = Model(mesh, ElementMaterials.uniform(len(mesh.tets), Material(10e3, 0.45)),
                  Loading(constraints, [_edged_plate(distance, slaves=top)]))
    solution = solve(model, device="cpu", relaxation=DynamicRelaxation(load_iterations=400, tolerance_mm=1e-3))
    assert solution.ok, solution.message
    return mesh, model, solution


def test_an_edge_beyond_the_contact_nodes_changes_nothing():
    _, _, unbounded = _pressed_block(None)
    _, _, far = _pressed_block(100.0)
    np.testing.assert_allclose(far.displacement, unbounded.displacement, atol=1e-5)
    np.testing.assert_allclose(far.plate_forces, unbounded.plate_forces, rtol=1e-5)


def test_nodes_pressed_by_a_rounded_edge_lie_on_it_and_the_rest_are_free():
    mesh, model, solution = _pressed_block(5.0)
    plate = model.loading.plates[0]
    final = mesh.nodes + solution.displacement
    top = plate.slave_nodes
    gaps = plate.gaps(final[top] - plate.displacement)  # against the plate at its final position
    assert gaps.min() > -1e-4  # nothing inside the plate, on the face or on the fillet
    x0 = mesh.nodes[top, 0]
    assert np.abs(gaps[x0 <= 4.0]).max() < 1e-4  # the flat face presses its nodes down PUSH mm
    np.testing.assert_allclose(final[top[x0 <= 4.0], 2], SIDE - PUSH, atol=1e-4)
    # the fillet rises from SIDE - PUSH at x = 5 to SIDE - PUSH + 4 at x = 9: the surface there
    # follows it (in contact) and climbs; the far corner, past the plate, bulges above the face
    order = np.argsort(final[top, 0])
    edge_zone = (final[top, 0] > 5.2) & (final[top, 0] < 7.0) & (mesh.nodes[top, 1] < 9.0)
    assert np.abs(gaps[edge_zone]).max() < 1e-3
    assert final[top[order[-1]], 2] > SIDE - PUSH + 0.2
    # frictionless contact on the fillet pushes the tissue away from the plate's interior (+x)
    force = solution.plate_forces[0]
    assert force[2] < 0 and force[0] > 0.01 * abs(force[2])
    assert abs(force[1]) < 1e-3 * abs(force[2])


def test_case_files_carry_the_edge():
    from BreastBiomechLib.io.cases import case_from_dict

    mesh = box_mesh((SIDE, SIDE, SIDE), (2, 2, 2))
    plate = {"name": "top", "point": [0, 0, SIDE], "normal": [0, 0, -1], "displacement": [0, 0, -1],
             "slaves": "face_zhi", "edge": {"direction": [1, 0, 0], "distance": 5.0, "radius": 3.0}}
    case = {"mesh": "m.vtu", "materials": {"default": {"E": 10e3, "nu": 0.45}}, "plates": [plate]}
    model, _ = case_from_dict(case, mesh)
    edge = model.loading.plates[0].edge
    assert edge.to_dict() == plate["edge"]
    json.dumps(edge.to_dict())
    del plate["edge"]["radius"]
    with pytest.raises(ValueError, match=r"plate top: its edge needs \['radius'\]"):
        case_from_dict(case, mesh)


def test_the_static_reference_refuses_edged_plates():
    from BreastBiomechLib.solver.static import solve_static

    mesh = box_mesh((SIDE, SIDE, SIDE), (1, 1, 1))
    model = Model(mesh, ElementMaterials.uniform(len(mesh.tets), Material(10e3, 0.45)),
                  Loading([], [_edged_plate(5.0, slaves=np.flatnonzero(mesh.point_data["face_zhi"]))]))
    with pytest.raises(ValueError, match="flat unbounded plates only"):
        solve_static(model)
