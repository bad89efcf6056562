"""Plate pose (placement.posed_plate): tilt about the plate's two in-plane axes through its final
point and an offset along its normal; the posed plate starts touching the tissue. Case files
carry friction, tilt and offset with clear errors; a batch solves one pose per model."""

from __future__ import annotations

import json

import numpy as np
import pytest

from BreastBiomechLib.mesh.primitives import box_mesh
from BreastBiomechLib.solver import DynamicRelaxation, Plate, solve, solve_batch
from BreastBiomechLib.solver.model import PlateEdge
from BreastBiomechLib.solver.placement import posed_plate, tilt_axes


def _top_plate(mesh, travel=1.0, edge=None):
    top = np.flatnonzero(mesh.point_data["face_zhi"])
    return Plate([5.0, 5.0, 10.0], [0, 0, -1], [0, 0, -travel], top, "top", edge)


def test_tilt_turns_the_final_plane_about_its_point_and_the_plate_starts_touching():
    mesh = box_mesh((10.0, 10.0, 10.0), (4, 4, 4))
    plate = _top_plate(mesh)
    first, second = tilt_axes(plate)
    np.testing.assert_allclose([first @ plate.normal, second @ plate.normal, first @ second], 0.0, atol=1e-12)
    np.testing.assert_allclose(first, [0, 1, 0])  # no edge: the in-plane part of LPS +y
    posed = posed_plate(plate, mesh.nodes, tilt_deg=(2.0, 0.0), offset_mm=0.5)
    angle = np.radians(2.0)  # right-handed about +y: (0, 0, -1) turns to (-sin, 0, -cos)
    np.testing.assert_allclose(posed.normal, [-np.sin(angle), 0.0, -np.cos(angle)], atol=1e-12)
    final = posed.point + posed.displacement
    np.testing.assert_allclose(final, plate.point + plate.displacement + 0.5 * posed.normal, atol=1e-12)
    gaps = posed.gaps(mesh.nodes[posed.slave_nodes])
    assert gaps.min() == pytest.approx(0.0, abs=1e-9)  # starts just touching its contact nodes
    np.testing.assert_allclose(np.cross(posed.displacement, posed.normal), 0.0, atol=1e-12)
    # a zero pose gives the plate back
    same = posed_plate(plate, mesh.nodes)
    np.testing.assert_allclose([same.point, same.normal, same.displacement], [plate.point, plate.normal,
                                                                              plate.displacement], atol=1e-12)
    # an edged plate turns about its edge direction first, and the edge turns with it
    edged = _top_plate(mesh, edge=PlateEdge([1, 0, 0], 3.0, 2.0))
    np.testing.assert_allclose(tilt_axes(edged)[0], [1, 0, 0])
    turned = posed_plate(edged, mesh.nodes, tilt_deg=(0.0, 1.5))
    assert abs(turned.edge.direction @ turned.normal) < 1e-12 and turned.edge.distance == 3.0


def test_a_held_plate_placed_onto_the_tissue_to_rounding_takes_a_pose():
    """The seed's rig's held plate is moved onto the skin until it is within
    TOUCH_TOLERANCE_MM of it (placement.held_plates_touching); posing it untilted, or tilting it
    about its final point, must not take that rounding for a plate that never touches."""
    from BreastBiomechLib.solver.placement import TOUCH_TOLERANCE_MM, held_plates_touching

    mesh = box_mesh((10.0, 10.0, 10.0), (4, 4, 4))
    top = np.flatnonzero(mesh.point_data["face_zhi"])
    [held] = held_plates_touching(mesh.nodes, [Plate([5.0, 5.0, 10.0 + 0.5 * TOUCH_TOLERANCE_MM], [0, 0, -1],
                                                      [0, 0, 0], top, "held")], top)
    assert 0.0 < held.gaps(mesh.nodes[top]).min() <= TOUCH_TOLERANCE_MM
    untilted = posed_plate(held, mesh.nodes)
    np.testing.assert_allclose(untilted.displacement, 0.0)
    tilted = posed_plate(held, mesh.nodes, (0.5, 0.0))
    assert tilted.displacement @ tilted.normal > 0.0  # half of it turns into the tissue: it moves


@pytest.mark.parametrize("tilt, offset, match", [((11.0, 0.0), 0.0, "more than 10"), ((0.0,), 0.0, "two finite"),
                                                 ((float("nan"), 0.0), 0.0, "two finite"),
                                                 ((0.0, 0.0), -20.0, "20 mm is more than 10")])
def test_bad_poses_are_refused(tilt, offset, match):
    mesh = box_mesh((10.0, 10.0, 10.0), (2, 2, 2))
    with pytest.raises(ValueError, match=match):
        posed_plate(_top_plate(mesh), mesh.nodes, tilt, offset)


def test_a_tilted_plate_presses_one_side_more_and_a_batch_takes_a_pose_per_model():
    mesh = box_mesh((10.0, 10.0, 10.0), (4, 4, 4))
    from BreastBiomechLib.solver import Constraint, ElementMaterials, Loading, Material, Model

    bottom = np.flatnonzero(mesh.point_data["face_zlo"])
    plate = _top_plate(mesh)
    model = Model(mesh, ElementMaterials.uniform(len(mesh.tets), Material(10e3, 0.45)),
                  Loading([Constraint.fixed(bottom)], [plate], total_time=0.2))
    poses = [[posed_plate(plate, mesh.nodes, (t, 0.0))] for t in (0.0, 5.0)]
    relaxation = DynamicRelaxation(load_iterations=300)
    flat, tilted = solve_batch(model, [model.materials] * 2, device="cpu", relaxation=relaxation, plates=poses)
    assert flat.ok and tilted.ok
    top = plate.slave_nodes
    # turned 5 degrees about +y through x = 5 mm: the x = 0 and x = 10 mm edges end tan(5 deg) x 10 mm apart
    x = mesh.nodes[top, 0]
    low_side, high_side = tilted.displacement[top[x < 1], 2].mean(), tilted.displacement[top[x > 9], 2].mean()
    assert low_side - high_side == pytest.approx(10.0 * np.tan(np.radians(5.0)), rel=0.1)
    assert np.ptp(flat.displacement[top, 2]) < 1e-3
    alone = solve(Model(mesh, model.materials, Loading(model.loading.constraints, poses[1], total_time=0.2)),
                  device="cpu", relaxation=relaxation)
    np.testing.assert_allclose(tilted.displacement, alone.displacement, atol=1e-5)
    np.testing.assert_allclose(tilted.plate_normals[0], poses[1][0].normal)


def _case(tmp_path, mesh, **plate):
    from BreastBiomechLib.io.meshes import write_vtu

    write_vtu(tmp_path / "block.vtu", mesh)
    spec = {"name": "top", "point": [5, 5, 10], "normal": [0, 0, -1], "displacement": [0, 0, -1],
            "slaves": np.flatnonzero(mesh.point_data["face_zhi"]).tolist(), **plate}
    data = {"mesh": "block.vtu", "materials": {"default": {"E": 10e3, "nu": 0.45}},
            "constraints": [{"nodes": np.flatnonzero(mesh.point_data["face_zlo"]).tolist()}], "plates": [spec]}
    path = tmp_path / "case.json"
    path.write_text(json.dumps(data))
    return path


def test_case_files_carry_friction_tilt_and_offset(tmp_path):
    from BreastBiomechLib.io.cases import read_case

    mesh = box_mesh((10.0, 10.0, 10.0), (2, 2, 2))
    model, _ = read_case(_case(tmp_path, mesh, friction=0.4, tilt_deg=[0.5, -0.3], offset_mm=0.2))
    plate = model.loading.plates[0]
    assert plate.friction == 0.4
    reference = posed_plate(_top_plate(mesh), mesh.nodes, (0.5, -0.3), 0.2)
    np.testing.assert_allclose(plate.normal, reference.normal)
    np.testing.assert_allclose(plate.point + plate.displacement, reference.point + reference.displacement)


@pytest.mark.parametrize("plate, match", [({"friction": -0.2}, "friction coefficient"),
                                          ({"friction": "high"}, "friction must be a number"),
                                          ({"tilt_deg": [12, 0]}, "12 degrees is more than 10"),
                                          ({"offset_mm": "far"}, "offset_mm must be a number"),
                                          ({"grip": 1}, "unknown fields"),
                                          ({"point": None}, "plate top: point must be three numbers")])
def test_bad_plate_entries_in_case_files_are_refused(tmp_path, plate, match):
    from BreastBiomechLib.io.cases import read_case

    mesh = box_mesh((10.0, 10.0, 10.0), (2, 2, 2))
    with pytest.raises(ValueError, match=match) as error:
        read_case(_case(tmp_path, mesh, **plate))
    assert "case.json" in str(error.value)


def test_bad_gravity_is_refused(tmp_path):
    from BreastBiomechLib.io.cases import case_from_dict

    mesh = box_mesh((10.0, 10.0, 10.0), (2, 2, 2))
    with pytest.raises(ValueError, match="gravity must be three finite"):
        case_from_dict({"materials": {"default": {"E": 1e3, "nu": 0.4}}, "gravity": [0, float("inf"), 0]}, mesh)


def test_niftysim_and_the_static_reference_refuse_friction(tmp_path):
    from BreastBiomechLib.io.cases import read_case
    from BreastBiomechLib.io.niftysim import write_niftysim
    from BreastBiomechLib.solver.static import solve_static

    mesh = box_mesh((10.0, 10.0, 10.0), (2, 2, 2))
    model, _ = read_case(_case(tmp_path, mesh, friction=0.3))
    with pytest.raises(ValueError, match="frictionless"):
        write_niftysim(tmp_path / "model.xml", model)
    with pytest.raises(ValueError, match="frictionless"):
        solve_static(model)


def test_a_plate_a_pose_change_lifts_off_a_curved_breast_stays_put_for_the_other_plate_to_push_onto():
    from BreastBiomechLib.solver.placement import posed_plate

    # a dome: the held plate above it touches its top node only, its point 30 mm to the side
    mesh = box_mesh((40.0, 40.0, 10.0), (8, 8, 2))
    nodes = mesh.nodes.copy()
    r2 = (nodes[:, 0] - 20.0) ** 2 + (nodes[:, 1] - 20.0) ** 2
    nodes[:, 2] += 5.0 * np.exp(-r2 / 200.0) * (nodes[:, 2] > 9.0)
    top = np.flatnonzero(nodes[:, 2] > 9.0)
    held = Plate([50.0, 20.0, nodes[top, 2].max()], [0, 0, -1], [0, 0, 0], top, "held")
    assert abs(held.gaps(nodes[top]).min()) < 1e-9
    # turned 1 degree about its point: its plane rises over the dome's top by about 30 mm x 1 degree
    tilt = (1.0, 0.0) if posed_plate(held, nodes, (1.0, 0.0)).gaps(nodes[top]).min() > 0 else (-1.0, 0.0)
    turned = posed_plate(held, nodes, tilt)
    stand_off = turned.gaps(nodes[top]).min()
    assert 0.2 < stand_off < 0.6 and np.allclose(turned.displacement, 0.0)
    np.testing.assert_allclose(turned.point, held.point)
    # turned and moved 2 mm away from the tissue (a tilt candidate's secant, a refit): it stays
    # there too, its stand-off the turn's and the offset's
    away = posed_plate(held, nodes, tilt, offset_mm=-2.0)
    assert np.allclose(away.displacement, 0.0)
    assert away.gaps(nodes[top]).min() == pytest.approx(stand_off + 2.0, abs=0.01)
    untilted_away = posed_plate(held, nodes, (0.0, 0.0), offset_mm=-2.0)
    assert untilted_away.gaps(nodes[top]).min() == pytest.approx(2.0, abs=1e-9)
    # a fitting mesh's held plate, which travels the little its recorded plane lies inside the
    # mesh (0.1 mm here), turned off the tissue by more than that: it ends there, without travel
    pressed = Plate(held.point, held.normal, 0.1 * held.normal, top, "held")
    pressed_turned = posed_plate(pressed, nodes, tilt)
    assert np.allclose(pressed_turned.displacement, 0.0)
    assert pressed_turned.gaps(nodes[top]).min() == pytest.approx(stand_off - 0.1, abs=0.01)
    # a plate recorded off the tissue (another frame) is refused, turned or not
    off = Plate([50.0, 20.0, nodes[top, 2].max() + 3.0], [0, 0, -1], [0, 0, 0], top, "held")
    for pose in ((0.0, 0.0), (1.0, 0.0), (-1.0, 0.0)):
        with pytest.raises(ValueError, match="short of the tissue"):
            posed_plate(off, nodes, pose)
