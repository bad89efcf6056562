"""NiftySim XML interop: a written model read back is the same model with the same solution; the
file means in NiftySim what the model means here (the TI fibre parameter, T4ANP across
materials, plates for its CPU build, settling); NiftySim's own constructs are read as its parser
reads them (start index + size, "all", SpecType NORMAL, UNIFORM/DIFFORM, per-constraint load
curves) or refused by name; the stable step counts the fibres. The NiftySim formulas used as
oracles are transcribed from its public source (tledMaterialTI.cpp, tledConstraint.cpp)."""

from __future__ import annotations

import warnings
import xml.etree.ElementTree as ET
from dataclasses import replace

import numpy as np
import pytest
import warp as wp

from BreastBiomechLib.io.niftysim import (NIFTYSIM_ETA_PER_ETA, NiftySimExportWarning, NiftySimFormatError,
                                         NiftySimImportWarning, read_niftysim, write_niftysim)
from BreastBiomechLib.mesh.primitives import box_mesh
from BreastBiomechLib.solver import (Constraint, DynamicRelaxation, ElementMaterials, Loading, Material, Model, Plate,
                                     solve)
from BreastBiomechLib.solver import kernels
from BreastBiomechLib.solver.model import LOAD_SHAPES, PlateEdge
from BreastBiomechLib.solver.geometry import shape_derivatives
from BreastBiomechLib.solver.host_setup import anp_slots, constraint_load_shapes, critical_time_step, merged_constraints
from BreastBiomechLib.solver.tled import internal_forces

SIDE = 10.0


def _model(settle_time=0.0, across=True, friction=0.0):
    mesh = box_mesh((SIDE, SIDE, SIDE), (3, 3, 3))
    upper = mesh.nodes[mesh.tets].mean(axis=1)[:, 2] > SIDE / 2
    materials = ElementMaterials.from_tissues(upper.astype(int) + 1, {
        1: Material(10e3, 0.45, prony=((0.3, 0.05),)),
        2: Material(20e3, 0.47, eta=2e3, fibre=(0.6, 0.0, 0.8), density=1050.0)})
    pd = mesh.point_data
    top = np.flatnonzero(pd["face_zhi"])
    pulled = top[(pd["face_xlo"][top] == 0) & (pd["face_ylo"][top] == 0)][:3]
    loading = Loading([Constraint.fixed(np.flatnonzero(pd["face_xlo"]), (True, False, False)),
                       Constraint.fixed(np.flatnonzero(pd["face_ylo"]), (False, True, False)),
                       Constraint(pulled, [[True, False, False]] * 3, [[0.2, 0, 0]] * 3)],
                      [Plate([0, 0, 0], [0, 0, 1], [0, 0, 0], np.flatnonzero(pd["face_zlo"]), "base"),
                       Plate([0, 0, SIDE], [0, 0, -1], [0, 0, -2.0], top, "top", friction=friction)],
                      gravity=[0, 0, -9.81], total_time=0.2, settle_time=settle_time)
    return Model(mesh, materials, loading, damping=200.0, formulation="T4ANP", anp_across_materials=across)


def _write(tmp_path, model, name="model.xml", **options):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NiftySimExportWarning)
        return write_niftysim(tmp_path / name, model, **options)


def test_round_trip_keeps_the_model_and_its_solution(tmp_path):
    model = _model()
    path = _write(tmp_path, model)
    root = ET.parse(path).getroot()
    assert root.find("Elements").get("Type") == "T4ANP"
    assert sorted(m.get("Type") for m in root.iter("Material")) == ["NHV", "TI"]
    assert len(root.findall("ContactPlate")) == 2
    back = read_niftysim(path)
    assert back.anp_across_materials
    np.testing.assert_allclose(back.mesh.nodes, model.mesh.nodes, atol=1e-9)
    np.testing.assert_array_equal(back.mesh.tets, model.mesh.tets)
    for name in ("mu", "kappa", "eta", "fibre", "density", "prony_g", "prony_tau"):
        np.testing.assert_allclose(getattr(back.materials, name), getattr(model.materials, name), rtol=1e-8)
    np.testing.assert_allclose(back.loading.gravity, model.loading.gravity)
    for p, q in zip(back.loading.plates, model.loading.plates):
        assert p.name == q.name
        np.testing.assert_allclose(p.normal, q.normal, atol=1e-12)
        assert abs(np.dot(p.point - q.point, q.normal)) < 1e-9  # same plane
        np.testing.assert_allclose(p.displacement, q.displacement, atol=1e-12)
        np.testing.assert_array_equal(p.slave_nodes, q.slave_nodes)
    a, b = solve(model, device="cpu"), solve(back, device="cpu")
    assert a.ok and b.ok
    np.testing.assert_allclose(b.displacement, a.displacement, atol=1e-5)


def _niftysim_ti_stress(F, M, K, E, a):
    """NiftySim's TI second Piola-Kirchhoff stress for its parameters M, K, E (tledMaterialTI)."""
    C = F.T @ F
    J = np.linalg.det(F)
    J23 = J ** (-2.0 / 3.0)
    A = np.outer(a, a)
    x2 = J23 * np.sum(A * C) - 1.0  # I4bar - 1
    Cinv = np.linalg.inv(C)
    iso = J23 * E * x2 * A - (E * x2 * (x2 + 1.0) + J23 * M * np.trace(C)) / 3.0 * Cinv + J23 * M * np.eye(3)
    return iso + K * J * (J - 1.0) * Cinv


def test_ti_fibre_parameter_means_in_niftysim_what_eta_means_here(tmp_path):
    """The file holds E = 2 eta, and NiftySim's stress for that E is this solver's for eta."""
    nodes = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]])
    tets = np.array([[0, 1, 2, 3]])
    from BreastBiomechLib.mesh.tetmesh import TetMesh

    mesh = TetMesh(nodes, tets)
    fibre = np.array([0.6, 0.0, 0.8])
    materials = ElementMaterials.from_tissues(np.ones(1, int), {1: Material(10e3, 0.45, eta=3e3, fibre=fibre)})
    model = Model(mesh, materials, Loading(total_time=0.1), formulation="T4")
    path = _write(tmp_path, model)
    params = np.array(ET.parse(path).getroot().find(".//ElasticParams").text.split(), float)
    assert params[2] == pytest.approx(NIFTYSIM_ETA_PER_ETA * 3e3)
    displacement = np.array([[0.0, 0, 0], [1.5, 0.4, 0], [0.2, -0.7, 0.3], [0.9, 0.1, 2.0]])
    ours = internal_forces(read_niftysim(path), displacement, device="cpu")
    dhdx, vol = shape_derivatives(nodes * 1e-3, tets)
    F = np.eye(3) + (displacement * 1e-3).T @ dhdx[0]
    S = _niftysim_ti_stress(F, *params[:3], fibre)
    theirs = np.array([vol[0] * F @ S @ dhdx[0, a] for a in range(4)])
    np.testing.assert_allclose(ours, theirs, rtol=2e-4, atol=1e-7 * np.abs(theirs).max())


def test_multi_material_t4anp_is_written_only_as_niftysims_anp(tmp_path):
    own = _model(across=False)
    with pytest.raises(NiftySimFormatError, match="averages nodal pressure across materials"):
        write_niftysim(tmp_path / "m.xml", own)
    assert read_niftysim(_write(tmp_path, _model(across=True))).anp_across_materials
    single = replace(own, materials=ElementMaterials.uniform(len(own.mesh.tets), Material(10e3, 0.45)))
    _write(tmp_path, single, "single.xml")  # one material: the same model either way
    # the option changes the averaging: one slot per node instead of one per node and material
    _, vol = shape_derivatives(own.mesh.nodes * 1e-3, own.mesh.tets)
    per_material = anp_slots(own.mesh.tets, [own.materials], vol)[1]
    across = anp_slots(own.mesh.tets, [own.materials], vol, across_materials=True)[1]
    assert len(across) == len(own.mesh.nodes) < len(per_material)
    u = np.zeros_like(own.mesh.nodes)
    u[:, 2] = -0.02 * own.mesh.nodes[:, 2]
    assert not np.allclose(internal_forces(own, u, "cpu"), internal_forces(replace(own, anp_across_materials=True), u,
                                                                            "cpu"), rtol=1e-3)


def test_cpu_build_export_prescribes_the_solved_contact_and_reaches_the_same_equilibrium(tmp_path):
    rough = _model(friction=0.5)
    # (the pulled top nodes are left out: the friction contact moves constrained slave nodes off
    # their prescribed tangential value, so that model's solution breaks its own constraint)
    model = replace(rough, anp_across_materials=False,
                    materials=ElementMaterials.uniform(len(rough.mesh.tets), Material(10e3, 0.45)),
                    loading=replace(rough.loading, constraints=rough.loading.constraints[:2]))
    with pytest.raises(NiftySimFormatError, match="frictionless"):
        write_niftysim(tmp_path / "plates.xml", model)
    relaxation = DynamicRelaxation(tolerance_mm=1e-4)
    solved = solve(model, device="cpu", relaxation=relaxation)
    assert solved.ok
    with pytest.warns(NiftySimExportWarning, match="solved displacement"):
        path = write_niftysim(tmp_path / "cpu.xml", model, solved_displacement=solved.displacement)
    root = ET.parse(path).getroot()
    assert not root.findall("ContactPlate")
    assert "any NiftySim build" in path.read_text().split("-->")[0]  # the file's first comment
    back = read_niftysim(path)
    assert not back.loading.plates
    again = solve(back, device="cpu", relaxation=relaxation)
    assert again.ok
    np.testing.assert_allclose(again.displacement, solved.displacement, atol=1e-4)
    with pytest.raises(NiftySimFormatError, match=r"\(27, 3\)|shape"):
        write_niftysim(tmp_path / "bad.xml", model, solved_displacement=np.zeros((3, 3)))


def test_settling_is_dropped_only_when_asked_and_says_so(tmp_path):
    with pytest.raises(NiftySimFormatError, match="no settling phase"):
        write_niftysim(tmp_path / "m.xml", _model(settle_time=0.1))
    with pytest.warns(NiftySimExportWarning, match="settling phase"):
        path = write_niftysim(tmp_path / "m.xml", _model(settle_time=0.1), drop_settling=True)
    assert "settling phase" in path.read_text().split("-->")[0]


def test_plates_keep_their_names_and_rounded_edges(tmp_path):
    model = _model()
    top = model.loading.plates[1]
    edged = replace(top, edge=PlateEdge((1.0, 0.0, 0.0), SIDE + 1.0, 3.0), name="cranial")
    model = replace(model, loading=replace(model.loading, plates=[model.loading.plates[0], edged]))
    with pytest.warns(NiftySimExportWarning, match="rounded edge"):
        path = write_niftysim(tmp_path / "edge.xml", model)
    back = read_niftysim(path).loading.plates[1]
    assert back.name == "cranial"
    np.testing.assert_allclose(back.edge.direction, edged.edge.direction, atol=1e-12)
    assert back.edge.distance == pytest.approx(edged.edge.distance, abs=1e-9)
    assert back.edge.radius == pytest.approx(3.0)
    assert abs((back.point - edged.point) @ edged.normal) < 1e-9


# --- NiftySim's own constructs, in files written by hand in its documented format ---------------

CUBE_NODES = "\n".join(" ".join(str(v) for v in row) for row in box_mesh((0.01, 0.01, 0.01), (1, 1, 1)).nodes)


def _cube(body: str, system: str = "", elements_type: str = "T4") -> str:
    mesh = box_mesh((0.01, 0.01, 0.01), (1, 1, 1))
    tets = "\n".join(" ".join(str(v) for v in row) for row in mesh.tets)
    return (f'<?xml version="1.0"?>\n<Model>\n<Nodes DOF="3" NumNodes="8">\n{CUBE_NODES}\n</Nodes>\n'
            f'<Elements NumEls="6" Type="{elements_type}">\n{tets}\n</Elements>\n{body}\n'
            f'<SystemParams><TimeStep>1e-4</TimeStep><TotalTime>0.1</TotalTime><DampingCoeff>50</DampingCoeff>'
            f'<Density>1000</Density>{system}</SystemParams>\n</Model>\n')


NH_ALL = '<ElementSet Size="all"><Material Type="NH"><ElasticParams NumParams="2">3000 50000</ElasticParams></Material></ElementSet>'


def _read(tmp_path, text: str, name="model.xml"):
    (tmp_path / name).write_text(text)
    return read_niftysim(tmp_path / name)


def test_element_sets_and_node_lists_by_start_index_size_and_all(tmp_path):
    sets = ('<ElementSet Size="2"><Material Type="NH"><ElasticParams NumParams="2">3000 50000</ElasticParams>'
            '</Material>0</ElementSet><ElementSet Size="4"><Material Type="TI"><ElasticParams NumParams="6">'
            '6000 90000 4000 0 0 2</ElasticParams><Density>1100</Density></Material>2</ElementSet>')
    body = sets + ('<Constraint DOF="all" NumNodes="4" Type="Fix"><Nodes>0</Nodes></Constraint>'
                   '<Constraint DOF="2" NumNodes="2" Type="Disp" LoadShape="RAMP"><Nodes>4 6</Nodes>'
                   '<Magnitudes Type="UNIFORM">0.001</Magnitudes></Constraint>')
    model = _read(tmp_path, _cube(body))
    np.testing.assert_array_equal(model.mesh.cell_data["material_set"], [1, 1, 2, 2, 2, 2])
    np.testing.assert_allclose(model.materials.eta, [0, 0, 2000, 2000, 2000, 2000])  # E / 2
    np.testing.assert_allclose(model.materials.fibre[2], [0, 0, 1])
    np.testing.assert_allclose(model.materials.density, [1000, 1000, 1100, 1100, 1100, 1100])
    fixed, disp = model.loading.constraints
    np.testing.assert_array_equal(fixed.nodes, [0, 1, 2, 3])  # a start index, not one node
    np.testing.assert_allclose(disp.values[:, 2], [1.0, 1.0])
    assert disp.load_shape == "RAMP"
    everything = _read(tmp_path, _cube(NH_ALL + '<Constraint NumNodes="all" Type="Fix"></Constraint>'))
    np.testing.assert_array_equal(everything.loading.constraints[0].nodes, np.arange(8))
    with pytest.raises(NiftySimFormatError, match="lists 3 nodes but its size says 4"):
        _read(tmp_path, _cube(NH_ALL + '<Constraint DOF="0" NumNodes="4" Type="Fix"><Nodes>0 1 2</Nodes></Constraint>'))
    with pytest.raises(NiftySimFormatError, match=r"size 'some'"):
        _read(tmp_path, _cube(NH_ALL.replace('Size="all"', 'Size="some"')))


def test_constraints_on_facets_facing_a_normal(tmp_path):
    body = NH_ALL + ('<Constraint DOF="all" Type="Fix" SpecType="NORMAL"><Normal ToleranceAngle="10">0 0 -1</Normal>'
                     '</Constraint>')
    model = _read(tmp_path, _cube(body))
    bottom = np.flatnonzero(np.isclose(model.mesh.nodes[:, 2], 0.0))
    np.testing.assert_array_equal(model.loading.constraints[0].nodes, bottom)
    with pytest.raises(NiftySimFormatError, match="ToleranceAngle"):
        _read(tmp_path, _cube(body.replace(' ToleranceAngle="10"', "")))


def test_magnitudes_uniform_and_diffform_counts(tmp_path):
    def disp(magnitudes):
        return NH_ALL + ('<Constraint DOF="0" NumNodes="2" Type="Disp" LoadShape="POLY345"><Nodes>1 3</Nodes>'
                         f'{magnitudes}</Constraint>')
    model = _read(tmp_path, _cube(disp('<Magnitudes Type="DIFFORM">0.001 0.002</Magnitudes>')))
    np.testing.assert_allclose(model.loading.constraints[0].values[:, 0], [1.0, 2.0])
    with pytest.raises(NiftySimFormatError, match="DIFFORM lists 3 magnitudes for 2 nodes"):
        _read(tmp_path, _cube(disp('<Magnitudes Type="DIFFORM">0.001 0.002 0.003</Magnitudes>')))
    with pytest.raises(NiftySimFormatError, match="UNIFORM magnitudes are one value"):
        _read(tmp_path, _cube(disp('<Magnitudes Type="UNIFORM">0.001 0.002</Magnitudes>')))
    with pytest.raises(NiftySimFormatError, match="not a number"):
        _read(tmp_path, _cube(disp('<Magnitudes Type="UNIFORM">one</Magnitudes>')))


def _load_factors(shape: int, times: np.ndarray) -> np.ndarray:
    @wp.kernel
    def evaluate(t: wp.array(dtype=float), shape: int, out: wp.array(dtype=float)):
        i = wp.tid()
        out[i] = kernels.load_factor(t[i], 1.0, shape)

    out = wp.zeros(len(times), dtype=float, device="cpu")
    wp.launch(evaluate, len(times), [wp.array(times.astype(np.float32), dtype=float, device="cpu"), shape, out],
              device="cpu")
    return out.numpy()


def test_load_curves_are_niftysims():
    r = np.linspace(0.0, 1.0, 41)
    expected = {"POLY345": r ** 3 * (10 - 15 * r + 6 * r ** 2), "RAMP": r, "STEP": np.ones_like(r),
                "RAMPHOLD": np.minimum(r / 0.1, 1.0), "HILLY": r * np.exp(np.cos(4 * np.pi * r) - 1)}
    for code, name in enumerate(LOAD_SHAPES):
        np.testing.assert_allclose(_load_factors(code, r), expected[name], atol=2e-6, err_msg=name)


def test_each_constraint_keeps_its_own_load_curve(tmp_path):
    """Two Disp constraints with different curves on one node: the solver drives each component
    with its own curve, the file keeps both, and the node ends where it is told."""
    body = NH_ALL + ('<Constraint DOF="all" Type="Fix" SpecType="NORMAL"><Normal ToleranceAngle="5">0 0 -1</Normal>'
                     '</Constraint>'
                     '<Constraint DOF="0" NumNodes="1" Type="Disp" LoadShape="STEP"><Nodes>7</Nodes>'
                     '<Magnitudes Type="UNIFORM">0.0004</Magnitudes></Constraint>'
                     '<Constraint DOF="1" NumNodes="1" Type="Disp" LoadShape="RAMP"><Nodes>7</Nodes>'
                     '<Magnitudes Type="UNIFORM">0.0004</Magnitudes></Constraint>')
    model = _read(tmp_path, _cube(body))
    assert [c.load_shape for c in model.loading.constraints] == [None, "STEP", "RAMP"]
    nodes, _, _ = merged_constraints(model)
    shapes = constraint_load_shapes(model, nodes)
    assert [LOAD_SHAPES[code] for code in shapes[list(nodes).index(7), :2]] == ["STEP", "RAMP"]
    written = ET.parse(_write(tmp_path, model, "again.xml")).getroot()
    assert sorted(c.get("LoadShape") for c in written.findall("Constraint") if c.get("Type") == "Disp") == ["RAMP", "STEP"]
    end = solve(model, device="cpu", relaxation=DynamicRelaxation())
    assert end.ok, end.message
    np.testing.assert_allclose(end.displacement[7, :2], [0.4, 0.4], atol=1e-5)
    clash = replace(model, loading=replace(model.loading, constraints=model.loading.constraints + [
        Constraint([7], [[True, False, False]], [[0.4, 0, 0]], load_shape="HILLY")]))
    with pytest.raises(ValueError, match="two load shapes"):
        constraint_load_shapes(clash, nodes)
    with pytest.raises(NiftySimFormatError, match="LoadShape 'SMOOTH'"):
        _read(tmp_path, _cube(body.replace('LoadShape="RAMP"', 'LoadShape="SMOOTH"')))
    with pytest.raises(NiftySimFormatError, match="needs a LoadShape"):
        _read(tmp_path, _cube(body.replace(' LoadShape="RAMP"', "")))


@pytest.mark.parametrize("body, system, message", [
    (NH_ALL + '<ContactSurface><VTKSurface>s.vtk</VTKSurface></ContactSurface>', "", "<ContactSurface>"),
    (NH_ALL + '<ContactCylinder/>', "", "<ContactCylinder>"),
    (NH_ALL + '<SubModel/>', "", "<SubModel>"),
    (NH_ALL + '<Constraint DOF="0" NumNodes="1" Type="Force" LoadShape="RAMP"><Nodes>1</Nodes></Constraint>', "",
     "type 'Force'"),
    (NH_ALL.replace('"NH"', '"AB"'), "", "material type 'AB'"),
    (NH_ALL, "<DoDeformableCollision>1</DoDeformableCollision>", "deformable-deformable contact"),
    (NH_ALL, "<Unknown>3</Unknown>", "<Unknown>"),
    (NH_ALL.replace('<Material Type="NH"><ElasticParams NumParams="2">3000 50000</ElasticParams>',
                    '<Material Type="NHV"><ElasticParams NumParams="2">3000 50000</ElasticParams>'
                    '<ViscoParams NumIsoTerms="1" NumVolTerms="1">0.3 0.1 0.2 0.5</ViscoParams>'), "",
     "volumetric visco terms"),
])
def test_what_cannot_be_represented_is_refused_by_name(tmp_path, body, system, message):
    with pytest.raises(NiftySimFormatError, match=message):
        _read(tmp_path, _cube(body, system))


def test_h8_meshes_are_refused_and_harmless_settings_warned(tmp_path):
    with pytest.raises(NiftySimFormatError, match="element type 'H8'"):
        _read(tmp_path, _cube(NH_ALL, elements_type="H8"))
    with pytest.warns(NiftySimImportWarning) as caught:
        _read(tmp_path, _cube(NH_ALL + '<Output Freq="10"><Variable>U</Variable></Output>',
                              "<HGKappa>0.075</HGKappa><DoDeformableCollision>0</DoDeformableCollision>"))
    assert {"<Output>" in str(w.message) or "HGKappa" in str(w.message) for w in caught} == {True}


def test_negatively_oriented_tets_are_renumbered(tmp_path):
    text = _cube(NH_ALL)
    mesh = box_mesh((0.01, 0.01, 0.01), (1, 1, 1))
    first = " ".join(str(v) for v in mesh.tets[0])
    flipped = " ".join(str(v) for v in mesh.tets[0][[0, 1, 3, 2]])
    model = _read(tmp_path, text.replace(first, flipped, 1))
    assert np.all(model.mesh.volumes > 0)
    assert sorted(model.mesh.tets[0]) == sorted(mesh.tets[0])


# --- the stable step counts the fibres --------------------------------------------------------

def test_stable_step_counts_the_fibre_stiffness():
    """The wave modulus behind the step is the kernels' own: a homogeneous uniaxial strain along
    the fibres stiffens by 16 eta / 9, and the critical step shrinks accordingly."""
    mesh = box_mesh((10.0, 10.0, 10.0), (1, 1, 1))
    E, nu, eta, strain = 10e3, 0.45, 30e3, 1e-4

    def axial_stress(eta_value):
        materials = ElementMaterials.uniform(len(mesh.tets), Material(E, nu, eta=eta_value, fibre=(1, 0, 0)))
        model = Model(mesh, materials, Loading(), formulation="T4")
        u = np.zeros_like(mesh.nodes)
        u[:, 0] = strain * mesh.nodes[:, 0]
        forces = internal_forces(model, u, device="cpu")
        face = mesh.point_data["face_xhi"] > 0
        return forces[face, 0].sum() / (10e-3 * 10e-3), model

    with_fibres, ti = axial_stress(eta)
    without, nh = axial_stress(0.0)
    assert (with_fibres - without) / strain == pytest.approx(16 * eta / 9, rel=2e-3)
    mu, kappa = nh.materials.mu[0], nh.materials.kappa[0]
    ratio = critical_time_step(ti, [ti.materials]) / critical_time_step(nh, [nh.materials])
    assert ratio == pytest.approx(np.sqrt((kappa + 4 * mu / 3) / (kappa + 4 * mu / 3 + 16 * eta / 9)), rel=1e-9)


# --- the command line ---------------------------------------------------------------------------

def test_cli_exports_a_case_for_either_build_and_runs_a_niftysim_model(tmp_path, capsys):
    import json

    from BreastBiomechLib.cli import main
    from BreastBiomechLib.io.meshes import read_vtu
    from test_simulate_case import _case

    path, mesh, _ = _case(tmp_path, settle_time=0.0, solver={"method": "relaxation", "device": "cpu"})
    assert main(["simulate", str(path), "--out", str(tmp_path / "solved"), "--quiet"]) == 0
    assert main(["niftysim", "export", str(path), "--out", str(tmp_path / "gpu.xml")]) == 0
    printed = capsys.readouterr().out
    assert "ContactPlates: NiftySim GPU build" in printed and "across materials" in printed
    assert main(["niftysim", "export", str(path), "--out", str(tmp_path / "cpu.xml"),
                 "--solved", str(tmp_path / "solved" / "deformed.vtu")]) == 0
    assert "any NiftySim build" in capsys.readouterr().out
    assert not ET.parse(tmp_path / "cpu.xml").getroot().findall("ContactPlate")
    assert main(["niftysim", "run", str(tmp_path / "cpu.xml"), "--out", str(tmp_path / "run"), "--quiet",
                 "--device", "cpu"]) == 0
    summary = json.loads((tmp_path / "run" / "solution.json").read_text())
    assert summary["status"] == "completed" and summary["max_displacement_mm"] > 1.0
    assert "displacement" in read_vtu(tmp_path / "run" / "deformed.vtu").point_data
    # refusals: exit 2 with the reason
    assert main(["niftysim", "run", str(tmp_path / "cpu.xml"), "--out", str(tmp_path / "run")]) == 2
    assert "not empty" in capsys.readouterr().err
    assert main(["niftysim", "export", str(path), "--out", str(tmp_path / "x.xml"), "--solved", str(path.parent / "block.vtu")]) == 2
    assert "not this case's solution" in capsys.readouterr().err
    (tmp_path / "h8.xml").write_text(_cube(NH_ALL, elements_type="H8"))
    assert main(["niftysim", "run", str(tmp_path / "h8.xml"), "--out", str(tmp_path / "h8")]) == 2
    assert "element type 'H8'" in capsys.readouterr().err

