"""Surfaces, TetGen meshing, quality report, tissue assignment and node sets (issue 4)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import SimpleITK as sitk
from images import oblique_direction
from meshing_fixtures import (BREAST_RADII, GLAND_CENTRE, GLAND_RADII, MUSCLE_Y, TUMOUR_CENTRE, TUMOUR_RADIUS,
                              breast_labels)

from BreastBiomechLib import labels as lt
from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels
from BreastBiomechLib.mesh.primitives import box_mesh
from BreastBiomechLib.mesh.quality import mesh_quality
from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.mesh.tissues import assign_tissues
from BreastBiomechLib.mesh.volume import TetGenSettings, tetrahedralize
from BreastBiomechLib.surface import SurfaceSettings, TriSurface, body_surface, check_surface, tissue_surface
from BreastBiomechLib.surface.extract import well_composed


@pytest.fixture(scope="module")
def labels():
    return breast_labels()


@pytest.fixture(scope="module")
def breast(labels):
    return mesh_labels(labels, MeshSettings(edge_mm=3.0))


def _voxel_volume_cm3(labels, mask) -> float:
    return float(mask.sum() * np.prod(labels.GetSpacing()) / 1000.0)


# -- surfaces ---------------------------------------------------------------------------------------

def test_body_surface_is_closed_oriented_and_keeps_the_volume(labels):
    surface, islands = body_surface(labels, SurfaceSettings(edge_mm=3.0))
    check = check_surface(surface)
    assert check.ok, check.problems()
    assert check.components == 1 and islands == 0
    voxels = _voxel_volume_cm3(labels, sitk.GetArrayViewFromImage(labels) > 0)
    assert surface.volume_mm3 / 1000.0 == pytest.approx(voxels, rel=0.02)  # blur rounds the cut slab edges
    assert 2.5 < surface.mean_edge_mm < 4.0


def test_tissue_surface_of_an_analytic_ellipsoid(labels):
    surface = tissue_surface(labels, lt.GLANDULAR.label, 2.0)
    assert check_surface(surface).ok
    exact = 4.0 / 3.0 * np.pi * (np.prod(GLAND_RADII) - TUMOUR_RADIUS**3) / 1000.0
    assert surface.volume_mm3 / 1000.0 == pytest.approx(exact, rel=0.03)
    # distance of the vertices to the ellipsoid (first order in F = |(x - c) / R|^2 - 1): within
    # the voxel staircase (half a 2.5 mm voxel at the flat poles), and well within it typically
    relative = surface.points - GLAND_CENTRE
    F = ((relative / GLAND_RADII) ** 2).sum(axis=1) - 1.0
    distance = np.abs(F) / (2.0 * np.linalg.norm(relative / GLAND_RADII**2, axis=1))
    # leave out where the muscle (y >= 0) cuts the ellipsoid's back and the tumour's cavity
    outer = (surface.points[:, 1] < -1.0) & (np.linalg.norm(surface.points - TUMOUR_CENTRE, axis=1) > TUMOUR_RADIUS + 1.5)
    assert distance[outer].max() < 1.5 and np.median(distance[outer]) < 0.3
    assert tissue_surface(labels, lt.SKIN.label, 2.0) is None  # absent tissue


def test_surface_follows_an_oblique_image_geometry():
    """The same anatomy on a rotated voxel grid gives the rotated surface (LPS mm)."""
    rotation = oblique_direction()
    straight = tissue_surface(breast_labels(), lt.GLANDULAR.label, 2.0)
    turned = tissue_surface(breast_labels(direction=rotation), lt.GLANDULAR.label, 2.0)
    assert turned.volume_mm3 == pytest.approx(straight.volume_mm3, rel=0.01)
    np.testing.assert_allclose(turned.points.mean(axis=0), rotation @ straight.points.mean(axis=0), atol=0.3)


def test_surface_checks_find_each_defect():
    closed, _ = body_surface(breast_labels(), SurfaceSettings(edge_mm=4.0))
    assert check_surface(closed).ok
    holed = TriSurface(closed.points, closed.triangles[1:])
    assert check_surface(holed).boundary_edges == 3
    assert "inwards" in " ".join(check_surface(closed.flipped()).problems())
    a, b, c = closed.triangles[0]
    extra = np.vstack([closed.points, closed.points[[a, b]].mean(axis=0) + 5.0])
    fin = TriSurface(extra, np.vstack([closed.triangles, [a, b, len(extra) - 1]]))
    assert check_surface(fin).nonmanifold_edges == 1
    mixed = closed.triangles.copy()
    mixed[0] = mixed[0][::-1]
    assert check_surface(TriSurface(closed.points, mixed)).misoriented_edges == 3
    # two tetrahedra sharing one vertex: closed, edge-manifold, but a bow-tie vertex
    tet = np.array([(0, 2, 1), (0, 1, 3), (1, 2, 3), (0, 3, 2)])
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1.0]])
    second = np.array([(0, 5, 4), (0, 4, 6), (4, 5, 6), (0, 6, 5)])
    bowtie = check_surface(TriSurface(points, np.vstack([tet, second])))
    assert bowtie.nonmanifold_vertices == 1 and bowtie.boundary_edges == 0


def test_well_composed_removes_critical_configurations():
    mask = np.zeros((4, 4, 4), bool)
    mask[1, 1, 1] = mask[2, 2, 2] = True  # touch at a corner only
    fixed = well_composed(mask)
    assert fixed[1:3, 1:3, 1:3].all() and mask.sum() == 2
    mask = np.zeros((3, 4, 4), bool)
    mask[1, 1, 1] = mask[1, 2, 2] = True  # touch along an edge only
    assert well_composed(mask)[1, 1:3, 1:3].all()


def test_empty_and_malformed_label_maps_get_clear_errors():
    empty = sitk.Image(20, 20, 10, sitk.sitkUInt8)
    with pytest.raises(ValueError, match="no labelled voxels"):
        mesh_labels(empty)
    flat = sitk.Image(20, 20, sitk.sitkUInt8)
    with pytest.raises(ValueError, match="3D"):
        body_surface(flat)
    odd = sitk.GetImageFromArray(np.full((6, 6, 6), 0.5, np.float32))
    with pytest.raises(ValueError, match="non-integer"):
        body_surface(odd)
    unknown = sitk.GetImageFromArray(np.pad(np.full((6, 6, 6), 9, np.uint8), 2))
    with pytest.raises(ValueError, match="outside the label table"):
        mesh_labels(unknown)


def test_defective_surface_is_refused_before_tetgen():
    surface, _ = body_surface(breast_labels(), SurfaceSettings(edge_mm=4.0))
    holed = TriSurface(surface.points, surface.triangles[1:])
    with pytest.raises(ValueError, match="boundary edges"):
        tetrahedralize(holed, np.zeros((0, 3)), TetGenSettings(edge_mm=4.0))


def test_a_mesh_too_fine_for_the_memory_is_refused_before_tetgen_with_the_edge_that_fits():
    """Resource limits (issue 28): TetGen's elements are bounded by the volume over the largest
    element allowed; a request beyond the memory limit is refused before TetGen starts, naming the
    smallest edge that fits, and that edge then meshes under the same limit."""
    import re

    from BreastBiomechLib.solver.memory import TooLargeForMemory, check_meshing_fits, meshing_elements

    surface, _ = body_surface(breast_labels(), SurfaceSettings(edge_mm=4.0))
    volume = abs(surface.volume_mm3)
    limit = check_meshing_fits(volume, 4.0) + 1  # just enough for 4 mm
    with pytest.raises(TooLargeForMemory, match=r"meshing the body surface \(\d+ cm3\) at 1 mm edges makes up to "
                                                r"about [\d,]+ elements .* memory limit given .* at least [\d.]+ mm") as refused:
        tetrahedralize(surface, np.zeros((0, 3)), TetGenSettings(edge_mm=1.0), memory_limit_bytes=limit)
    edge = float(re.search(r"at least ([\d.]+) mm", str(refused.value)).group(1))
    assert 1.0 < edge <= 4.1
    mesh = tetrahedralize(surface, np.zeros((0, 3)), TetGenSettings(edge_mm=edge), memory_limit_bytes=limit)
    assert 0 < len(mesh.tets) <= meshing_elements(volume, edge)  # the bound holds


# -- quality ----------------------------------------------------------------------------------------

def test_quality_measures_of_known_tetrahedra():
    regular = TetMesh([[1, 1, 1], [-1, 1, -1], [1, -1, -1], [-1, -1, 1]], [[0, 1, 2, 3]])
    assert regular.volumes[0] > 0
    q = mesh_quality(regular)
    assert q.shape_factor[0] == pytest.approx(1.0)
    assert q.min_face_angle_deg[0] == pytest.approx(60.0) and q.max_face_angle_deg[0] == pytest.approx(60.0)
    assert q.aspect_ratio[0] == pytest.approx(1.0)
    assert q.min_dihedral_deg[0] == pytest.approx(np.degrees(np.arccos(1 / 3)))
    corner = mesh_quality(TetMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 1, 2, 3]]))
    # circumradius sqrt(3)/2: optimal volume 8 R^3 / (9 sqrt 3) = 1/3, element volume 1/6
    assert corner.shape_factor[0] == pytest.approx(0.5)
    assert corner.max_dihedral_deg[0] == pytest.approx(90.0)
    assert corner.min_dihedral_deg[0] == pytest.approx(np.degrees(np.arccos(1 / np.sqrt(3))))
    sliver = mesh_quality(TetMesh([[0, 0, 0], [1, 0, 0], [1, 1, 0.001], [0, 1, 0]], [[0, 1, 2, 3]]))
    assert sliver.failing()["shape_factor"][0] and not sliver.failing()["aspect_ratio"][0]
    needle = mesh_quality(TetMesh([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0], [0, 0, 1]], [[0, 1, 2, 3]]))
    assert needle.failing()["aspect_ratio"][0] and needle.failing()["any"][0]
    assert mesh_quality(box_mesh((1, 1, 1), (2, 2, 2))).summary()["failing"]["any"]["count"] == 0


# -- tissue assignment --------------------------------------------------------------------------

def test_voxel_majority_is_exact_on_a_grid_aligned_mesh(oblique_geometry):
    """A Kuhn box mesh over a two-tissue label map: every voxel centre inside the box is counted
    once, and the fractions are the exact counts of centres in each tet."""
    origin, spacing, direction = oblique_geometry
    array = np.full((8, 12, 14), lt.FAT.label, np.uint8)
    array[:, :, 7:] = lt.GLANDULAR.label
    image = sitk.GetImageFromArray(array)
    image.SetOrigin(origin)
    image.SetSpacing(spacing)
    image.SetDirection(direction)
    D = np.asarray(direction).reshape(3, 3) * np.asarray(spacing)
    # the box covers voxel index ranges [0.3, 13.3] x [0.3, 11.3] x [0.3, 7.3] in the image's axes
    unit = box_mesh((13.0, 11.0, 7.0), (5, 4, 3), origin_mm=(0.3, 0.3, 0.3))
    mesh = TetMesh(np.asarray(origin) + unit.nodes @ D.T, unit.tets)
    result = assign_tissues(mesh, image)
    inside = result.element_of_voxel >= 0
    assert inside.sum() == 13 * 11 * 7  # voxel centres 1..13, 1..11, 1..7
    assert result.voxels.sum() == inside.sum()
    # brute force: the containing tet of each voxel centre by barycentric coordinates
    k, j, i = np.nonzero(inside)
    q = np.stack([i, j, k], axis=1).astype(float)
    p = unit.nodes[unit.tets]
    for centre, element in zip(q[::37], result.element_of_voxel[inside][::37]):
        T = np.stack([p[element, 1] - p[element, 0], p[element, 2] - p[element, 0], p[element, 3] - p[element, 0]], 1)
        lam = np.linalg.solve(T, centre - p[element, 0])
        assert lam.min() >= -1e-9 and lam.sum() <= 1 + 1e-9
    x_centre = np.asarray(unit.nodes[unit.tets].mean(axis=1))[:, 0]
    holds = result.voxels > 0
    expected = np.where(x_centre < 6.5, lt.FAT.label, lt.GLANDULAR.label)
    split = np.abs(x_centre - 6.5) < 3.0  # tets straddling x = 6.5 vote by counts; check the others
    np.testing.assert_array_equal(result.tissue[holds & ~split], expected[holds & ~split])
    np.testing.assert_allclose(result.fractions.sum(axis=1), 1.0)
    assert (result.voxels == 0).any()  # the small tets with no centre took the tissue at their centroid
    np.testing.assert_array_equal(result.tissue[~holds & ~split], expected[~holds & ~split])


# -- the whole pipeline ---------------------------------------------------------------------------

def test_breast_mesh_quality_and_tissues(breast, labels):
    summary = breast.summary()
    assert summary["quality"]["failing"]["any"]["count"] == 0, summary["quality"]
    assert summary["quality"]["dihedral_min_deg"] > 2.0
    mesh = breast.mesh
    assert (mesh.volumes > 0).all()
    voxels = _voxel_volume_cm3(labels, sitk.GetArrayViewFromImage(labels) > 0)
    assert summary["volume_cm3"] == pytest.approx(voxels, rel=0.02)  # as the body surface
    counts = summary["elements_per_tissue"]
    assert set(counts) == {"fat", "glandular", "muscle", "tumour"}
    for name, figures in summary["tissue_representation"].items():
        assert figures["dice"] > (0.85 if name == "tumour" else 0.95), (name, figures)
    tumour = mesh.nodes[mesh.tets[mesh.cell_data["tissue"] == lt.TUMOUR.label]].mean(axis=(0, 1))
    assert np.linalg.norm(tumour - TUMOUR_CENTRE) < 1.0
    assert 2.5 < np.cbrt(6 * np.sqrt(2) * np.median(mesh.volumes)) < 4.0  # elements of about the edge asked
    for name in ("tissue", "fraction_fat", "quality_shape_factor", "quality_fails"):
        assert name in mesh.cell_data


def test_interface_points_make_the_elements_follow_the_tissues(labels, breast):
    plain = mesh_labels(labels, MeshSettings(edge_mm=3.0, refine_interfaces=False))
    for name in ("glandular", "tumour"):
        assert breast.representation[name]["dice"] > plain.representation[name]["dice"] + 0.02


def test_node_sets(breast):
    mesh = breast.mesh
    chest, cut, skin = (mesh.node_set(n) for n in ("chest_wall", "fov_cut", "skin"))
    breast_skin, nipple = mesh.node_set("breast_skin"), mesh.node_set("nipple")
    assert len(set(chest) & set(skin)) == 0 and len(set(cut) & set(chest)) == 0
    inner = (np.abs(mesh.nodes[chest, 0]) < 40.0) & (np.abs(mesh.nodes[chest, 2]) < 34.0)  # off the cut edges
    np.testing.assert_allclose(mesh.nodes[chest[inner], 1], MUSCLE_Y[1], atol=0.6)  # the muscle's back face
    assert (mesh.nodes[chest, 1] > MUSCLE_Y[1] - 3.0).all()
    assert set(breast_skin) <= set(skin) and (mesh.nodes[breast_skin, 1] < MUSCLE_Y[1]).all()
    assert len(nipple) == 1
    np.testing.assert_allclose(mesh.nodes[nipple[0]], [0.0, -BREAST_RADII[1], 0.0], atol=1.5)
    # the cut faces lie on the field of view (x = +-46, z = +-40 mm)
    on_edge = (np.abs(np.abs(mesh.nodes[cut, 0]) - 46.0) < 0.55) | (np.abs(np.abs(mesh.nodes[cut, 2]) - 40.0) < 1.3)
    assert on_edge.all() and len(cut) > 50


def test_small_tissue_is_reported_not_meshed():
    image = breast_labels()
    array = sitk.GetArrayFromImage(image)
    array[array == lt.TUMOUR.label] = lt.GLANDULAR.label
    array[20, 18, 46] = lt.TUMOUR.label  # one voxel
    small = sitk.GetImageFromArray(array)
    small.CopyInformation(image)
    result = mesh_labels(small, MeshSettings(edge_mm=4.0))
    assert any("tumour: 1 voxels" in note for note in result.notes)


def test_cli_mesh_writes_mesh_case_and_niftysim(tmp_path, labels, capsys):
    from BreastBiomechLib.cli import main
    from BreastBiomechLib.io.cases import read_case
    from BreastBiomechLib.io.images import write_image
    from BreastBiomechLib.io.meshes import read_vtu
    from BreastBiomechLib.io.niftysim import read_niftysim

    write_image(tmp_path / "labels.nrrd", labels)
    assert main(["mesh", str(tmp_path / "labels.nrrd"), "--out", str(tmp_path / "out"), "--edge-mm", "4",
                 "--compression", "0.3", "--quiet"]) == 0
    printed = capsys.readouterr().out
    # how model.xml differs from case.json, said every time: rounded edges, settling, ANP
    for difference in ("NiftySim plates are flat rectangles", "settling phase", "across materials"):
        assert "model.xml: " in printed and difference in printed, difference
    out = tmp_path / "out"
    mesh = read_vtu(out / "mesh.vtu")
    assert {"tissue", "fraction_glandular", "quality_min_dihedral_deg"} <= set(mesh.cell_data)
    assert {"chest_wall", "skin", "breast_skin", "fov_cut", "nipple"} <= set(mesh.point_data)
    report = json.loads((out / "mesh_report.json").read_text())
    assert report["elements"] == len(mesh.tets)
    model, settings = read_case(out / "case.json")
    left, right = sorted(model.loading.plates, key=lambda p: p.point[0])
    gap = right.point[0] - left.point[0]
    assert gap == pytest.approx(2 * BREAST_RADII[0], abs=1.5)  # tangent to the breast, not the chest
    travel = np.linalg.norm(left.displacement) + np.linalg.norm(right.displacement)
    assert travel == pytest.approx(0.3 * gap)
    # the plates' flat faces end the plate travel (12 mm) anterior to the chest, in a rounded
    # edge of that radius reaching back to the chest: they may touch all the breast skin
    # between them, none of the chest's
    breast_skin = mesh.node_set("breast_skin")
    front = mesh.nodes[np.unique(mesh.tets[mesh.cell_data["tissue"] == lt.MUSCLE.label]), 1].min()
    for plate in (left, right):
        assert plate.edge.direction == pytest.approx([0.0, 1.0, 0.0])
        assert plate.point[1] + plate.edge.distance == pytest.approx(front - 0.15 * gap)
        assert plate.edge.radius == pytest.approx(0.15 * gap)
    contact = left.slave_nodes
    between = (mesh.nodes[breast_skin, 0] >= left.point[0]) & (mesh.nodes[breast_skin, 0] <= right.point[0])
    assert set(contact) == set(breast_skin[between])

    # and the case solves with its heterogeneous default materials (muscle and tumour 10x fat)
    from BreastBiomechLib.solver import solve

    assert np.ptp(model.materials.mu) > 0
    solution = solve(model, device="cpu", relaxation=settings.relaxation)
    assert solution.status == "completed", solution.message
    final = mesh.nodes + solution.displacement
    for i, plate in enumerate(model.loading.plates):
        assert plate.gaps(final[plate.slave_nodes] - plate.displacement).min() > -1e-2
        assert solution.plate_forces[i] @ plate.normal > 1.0

    nifty = read_niftysim(out / "model.xml")
    assert len(nifty.mesh.tets) == len(mesh.tets) and len(nifty.loading.plates) == 2
    assert nifty.anp_across_materials and "settling phase" in (out / "model.xml").read_text().split("-->")[0]
    for name in ("body", "glandular", "muscle", "tumour"):
        assert (out / "surfaces" / f"{name}.vtp").is_file()
    assert main(["mesh", str(tmp_path / "missing.nrrd"), "--out", str(out)]) == 2


def test_flat_boundary_caps_are_removed_even_where_they_pass_the_quality_criteria():
    """A cap (an element with two or more faces on the boundary: all its nodes on the surface)
    lies almost in the surface; a plate flattening the surface there flattens it to zero volume.
    One 0.4 mm high on a 5 mm face (smallest dihedral 13.5 degrees) passes the seed's criteria
    and is kept by the 5-degree sliver rule alone, but is removed as flatter than 15 degrees;
    the box's own corner elements (caps of 45-90 degrees) stay."""
    from BreastBiomechLib.mesh.improve import improve_quality
    from BreastBiomechLib.mesh.primitives import box_mesh
    from BreastBiomechLib.mesh.quality import mesh_quality
    from BreastBiomechLib.mesh.tetmesh import TetMesh, boundary_faces

    box = box_mesh((10.0, 10.0, 10.0), (2, 2, 2))
    faces, _ = boundary_faces(box.tets)
    top = next(f for f in faces if np.allclose(box.nodes[f][:, 2], 10.0))
    nodes = np.vstack([box.nodes, box.nodes[top].mean(axis=0) + [0.0, 0.0, 0.4]])
    cap = np.array([*top, len(box.nodes)])
    p = nodes[cap]
    if np.dot(np.cross(p[1] - p[0], p[2] - p[0]), p[3] - p[0]) < 0:
        cap = cap[[1, 0, 2, 3]]
    mesh = TetMesh(nodes, np.vstack([box.tets, cap]))
    quality = mesh_quality(mesh)
    assert not quality.failing()["any"][-1] and 5.0 < quality.min_dihedral_deg[-1] < 15.0
    repaired, done = improve_quality(mesh)
    assert done["caps_removed"] == 1 and len(repaired.tets) == len(box.tets) and len(repaired.nodes) == len(box.nodes)
    assert improve_quality(mesh, cap_dihedral_deg=5.0)[1]["caps_removed"] == 0
    assert improve_quality(box)[1]["caps_removed"] == 0


def test_pulled_corners_put_the_stair_surface_on_the_ellipsoid():
    """``hemi_ellipsoid_mesh(pull_corners=True)``: the same elements; most nodes that were outside
    the ellipsoid now on it, along the ray from its centre; every other node where it was; no
    element flattened under a tenth of its volume (the corners whose pull would do that stay)."""
    from BreastBiomechLib.mesh.primitives import hemi_ellipsoid_mesh

    radii = np.array([50.0, 40.0, 45.0])
    stair = hemi_ellipsoid_mesh(radii, 5.0)
    pulled = hemi_ellipsoid_mesh(radii, 5.0, pull_corners=True)
    np.testing.assert_array_equal(pulled.tets, stair.tets)
    q_stair = ((stair.nodes / radii) ** 2).sum(axis=1)
    q_pulled = ((pulled.nodes / radii) ** 2).sum(axis=1)
    outside = q_stair > 1.0
    moved = np.any(pulled.nodes != stair.nodes, axis=1)
    assert outside.sum() > 100 and moved.sum() > 0.8 * outside.sum()  # the stairs' corners, most pulled
    assert not np.any(moved & ~outside)
    np.testing.assert_allclose(q_pulled[moved], 1.0, rtol=1e-12)
    np.testing.assert_allclose(np.cross(pulled.nodes[moved], stair.nodes[moved]), 0.0, atol=1e-9)  # same ray
    assert np.all(pulled.volumes >= 0.1 * stair.volumes)
