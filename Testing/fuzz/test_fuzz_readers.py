"""Every reader fuzzed (hypothesis): case files, NiftySim XML, Slicer markups, .vtu meshes, label
maps, a fit's evaluation log and a study's rows. Each generated file is either read into a valid
result with no NaN in it, or refused with the project's own InputError naming the file; never
another exception (numpy, VTK, SimpleITK, XML, KeyError, ...).

The inputs are valid files mutated: JSON values replaced by anything JSON can hold (NaN and
infinities too), keys dropped, text cut short or overwritten; meshes with non-finite, inverted,
flat, duplicated and unused parts and other cell types; label maps written as NRRD headers by
hand (unknown labels, one voxel, empty, 2D, vectors, floats, huge or zero spacing, oblique and
non-orthonormal directions). ``BREASTBIOMECH_FUZZ_EXAMPLES`` sets how many inputs each target
tries (default 40, CI's); ``BREASTBIOMECH_FUZZ_LOG`` names a file that collects every refusal's
message, for counting the distinct ones (docs/reliability.md).
"""

from __future__ import annotations

import json
import math
import os
import re
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from BreastBiomechLib.errors import InputError
from BreastBiomechLib.io.cases import read_case
from BreastBiomechLib.io.images import read_image, read_label_map
from BreastBiomechLib.io.markups import read_markups, write_markups
from BreastBiomechLib.io.meshes import read_vtu, write_vtu
from BreastBiomechLib.io.niftysim import NiftySimImportWarning, read_niftysim, write_niftysim
from BreastBiomechLib.labels import FAT, GLANDULAR
from BreastBiomechLib.landmarks import Landmarks
from BreastBiomechLib.mesh.primitives import box_mesh
from BreastBiomechLib.optimisation.record import read_evaluations
from BreastBiomechLib.optimisation.study import ROW_FILE, read_study

EXAMPLES = int(os.environ.get("BREASTBIOMECH_FUZZ_EXAMPLES", "40"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=EXAMPLES <= 40,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                       HealthCheck.data_too_large])


def _log(target: str, message: str) -> None:
    log = os.environ.get("BREASTBIOMECH_FUZZ_LOG")
    if log:
        shape = re.sub(r"-?\d+(\.\d+)?(e[-+]?\d+)?", "N", message.split(": ", 1)[-1])  # numbers vary, text not
        with open(log, "a", errors="backslashreplace") as file:
            file.write(f"{target}\t{shape[:200]}\n")


def read_or_refuse(target: str, read, path):
    """``read(path)``'s result, or None where it refused with an InputError naming ``path``;
    any other exception fails the test."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NiftySimImportWarning)
            return read(path)
    except InputError as error:
        assert str(path) in str(error), f"the message does not name the file: {error}"
        assert "\n" not in str(error).strip(), f"not one line: {error!r}"
        _log(target, str(error))
        return None


def assert_finite(*arrays) -> None:
    for array in arrays:
        assert np.isfinite(np.asarray(array, dtype=np.float64)).all(), "NaN or infinity in a reader's result"


# --- mutations of JSON documents --------------------------------------------------------------

ANY_JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=12),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4),
    max_leaves=8)


def _mutate(data, document):
    """One mutation of a JSON ``document`` (a copy): a value somewhere replaced, a key dropped, a
    list emptied or given an extra item."""
    document = json.loads(json.dumps(document))
    parent, key = None, None
    node = document
    while isinstance(node, (dict, list)) and node and data.draw(st.booleans()):
        keys = list(node) if isinstance(node, dict) else list(range(len(node)))
        parent, key = node, data.draw(st.sampled_from(keys))
        node = node[key]
    action = data.draw(st.sampled_from(["replace", "drop", "empty", "extend"]))
    if parent is None:
        return data.draw(ANY_JSON) if action == "replace" else document
    if action == "replace":
        parent[key] = data.draw(ANY_JSON)
    elif action == "drop":
        del parent[key]
    elif action == "empty" and isinstance(node, (dict, list)):
        node.clear()
    elif action == "extend" and isinstance(node, list):
        node.append(data.draw(ANY_JSON))
    return document


def mutated_text(data, document) -> str:
    """A seed JSON document mutated one to three times, written out; sometimes cut short or with a
    stretch overwritten by arbitrary characters."""
    for _ in range(data.draw(st.integers(1, 3))):
        document = _mutate(data, document)
    text = json.dumps(document)  # NaN and Infinity written as Python's json does
    damage = data.draw(st.sampled_from(["none", "none", "cut", "overwrite"]))
    if damage == "cut":
        text = text[: data.draw(st.integers(0, max(0, len(text) - 1)))]
    elif damage == "overwrite":
        at = data.draw(st.integers(0, len(text)))
        text = text[:at] + data.draw(st.text(max_size=6)) + text[at + 3:]
    return text


# --- seeds ------------------------------------------------------------------------------------

def _block_mesh():
    mesh = box_mesh((10.0, 10.0, 10.0), (2, 2, 2))
    centres = mesh.nodes[mesh.tets].mean(axis=1)
    mesh.cell_data["tissue"] = np.where(centres[:, 2] < 5.0, FAT.label, GLANDULAR.label).astype(np.int32)
    return mesh


CASE = {
    "mesh": "block.vtu",
    "materials": {"fat": {"E": 10e3, "nu": 0.45}, "glandular": {"E": 20e3, "nu": 0.45, "eta": 2e3,
                                                              "fibre": [1, 0, 0]}},
    "constraints": [{"nodes": "face_xlo", "components": "x"}, {"nodes": "face_ylo", "components": [0, 1, 0]}],
    "plates": [{"name": "base", "point": [0, 0, 0], "normal": [0, 0, 1], "slaves": "face_zlo"},
               {"name": "top", "point": [0, 0, 10], "normal": [0, 0, -1], "displacement": [0, 0, -2.0],
                "slaves": "face_zhi"}],
    "total_time": 0.2, "settle_time": 0.1, "damping": 200.0,
    "solver": {"method": "relaxation", "device": "cpu"},
}


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    folder = tmp_path_factory.mktemp("block")
    write_vtu(folder / "block.vtu", _block_mesh())
    return folder


def _check_model(model) -> None:
    m = model.materials
    assert_finite(model.mesh.nodes, m.mu, m.kappa, m.eta, m.fibre, m.density)
    assert (model.mesh.volumes > 0).all()
    for plate in model.loading.plates:
        assert_finite(plate.point, plate.normal, plate.displacement)


# --- the targets ------------------------------------------------------------------------------

@FUZZ
@given(st.data())
def test_case_files(block, data):
    path = block / f"case-{data.draw(st.integers(0, 3))}.json"
    path.write_text(mutated_text(data, CASE))
    result = read_or_refuse("case", read_case, path)
    if result is not None:
        model, solver_settings = result
        _check_model(model)


@pytest.fixture(scope="module")
def niftysim_seed(block, tmp_path_factory):
    from dataclasses import replace

    model, _ = read_case(_write(block / "seed.json", json.dumps(dict(CASE, settle_time=0.0))))
    path = write_niftysim(tmp_path_factory.mktemp("niftysim") / "seed.xml", replace(model, anp_across_materials=True))
    return path.read_text()


def _write(path, text):
    path.write_text(text)
    return path


def _xml_mutation(data, text: str) -> str:
    """A NiftySim file with an element's text, an attribute or a stretch of characters changed."""
    numbers = list(re.finditer(r"-?\d+(\.\d+)?(e[-+]?\d+)?", text))
    attributes = list(re.finditer(r'(\w+)="([^"]*)"', text))
    elements = list(re.finditer(r"<(\w+)[^>]*>.*?</\1>", text, flags=re.S))
    actions = [a for a, there in (("number", numbers), ("attribute", attributes), ("element", elements)) if there]
    action = data.draw(st.sampled_from(actions + ["cut", "overwrite"]))
    if action == "number":
        match = data.draw(st.sampled_from(numbers))
        new = data.draw(st.sampled_from(["nan", "inf", "-1", "0", "1e308", "x", "", "3.5", "999999"]))
        return text[:match.start()] + new + text[match.end():]
    if action == "attribute":
        match = data.draw(st.sampled_from(attributes))
        return text[:match.start(2)] + data.draw(st.text(max_size=6).filter(lambda s: '"' not in s)) + text[match.end(2):]
    if action == "element":
        match = data.draw(st.sampled_from(elements))
        return text[:match.start()] + text[match.end():]
    at = data.draw(st.integers(0, len(text)))
    return text[:at] if action == "cut" else text[:at] + data.draw(st.text(max_size=8)) + text[at + 4:]


@FUZZ
@given(st.data())
def test_niftysim_models(niftysim_seed, tmp_path_factory, data):
    text = niftysim_seed
    for _ in range(data.draw(st.integers(1, 3))):
        text = _xml_mutation(data, text)
    path = _write(tmp_path_factory.getbasetemp() / "fuzz.xml", text)
    model = read_or_refuse("niftysim", read_niftysim, path)
    if model is not None:
        _check_model(model)


@pytest.fixture(scope="module")
def markups_seed(tmp_path_factory):
    landmarks = Landmarks(np.array([[1.0, 2.0, 3.0], [-4.0, 5.5, 6.0]]), ["a", "b"], ["", "nipple"])
    path = write_markups(tmp_path_factory.mktemp("markups") / "seed.mrk.json", landmarks)
    return json.loads(path.read_text())


@FUZZ
@given(st.data())
def test_markups(markups_seed, tmp_path_factory, data):
    path = _write(tmp_path_factory.getbasetemp() / "fuzz.mrk.json", mutated_text(data, markups_seed))
    landmarks = read_or_refuse("markups", read_markups, path)
    if landmarks is not None:
        assert_finite(landmarks.positions)
        assert landmarks.positions.shape == (len(landmarks.labels), 3)


def _broken_mesh(data):
    """A block mesh with one defect drawn (or none), as VTK writes it."""
    import vtk

    mesh = _block_mesh()
    defect = data.draw(st.sampled_from(["none", "nan", "inf", "inverted", "flat", "duplicate", "unused", "no tets",
                                        "cell type", "nan cell data", "out of range"]))
    if defect in ("nan", "inf"):
        mesh.nodes[data.draw(st.integers(0, len(mesh.nodes) - 1)), data.draw(st.integers(0, 2))] = float(defect)
    elif defect == "inverted":
        k = data.draw(st.integers(0, len(mesh.tets) - 1))
        mesh.tets[k, [0, 1]] = mesh.tets[k, [1, 0]]
    elif defect == "flat":
        tet = mesh.tets[data.draw(st.integers(0, len(mesh.tets) - 1))]
        tet[3] = tet[2]
    elif defect == "duplicate":
        mesh.tets = np.vstack([mesh.tets, mesh.tets[:1]])
        mesh.cell_data = {k: np.concatenate([v, v[:1]]) for k, v in mesh.cell_data.items()}
    elif defect == "unused":
        mesh.nodes = np.vstack([mesh.nodes, [[50.0, 50.0, 50.0]]])
        mesh.point_data = {k: np.concatenate([v, v[:1]]) for k, v in mesh.point_data.items()}
    elif defect == "nan cell data":
        mesh.cell_data["tissue"] = mesh.cell_data["tissue"].astype(np.float64)
        mesh.cell_data["tissue"][0] = np.nan
    grid = mesh.to_vtk()
    if defect == "no tets":
        grid = vtk.vtkUnstructuredGrid()
        grid.SetPoints(mesh.to_vtk().GetPoints())
    elif defect == "cell type":
        triangle = vtk.vtkIdList()
        for node in mesh.tets[0][:3]:
            triangle.InsertNextId(int(node))
        grid.InsertNextCell(vtk.VTK_TRIANGLE, triangle)
    elif defect == "out of range":
        ids = vtk.vtkIdList()
        for node in (0, 1, 2, len(mesh.nodes) + 5):
            ids.InsertNextId(node)
        grid.InsertNextCell(vtk.VTK_TETRA, ids)
    return grid, defect


@FUZZ
@given(st.data())
def test_vtu_meshes(tmp_path_factory, data):
    import vtk

    grid, defect = _broken_mesh(data)
    path = tmp_path_factory.getbasetemp() / "fuzz.vtu"
    writer = vtk.vtkXMLUnstructuredGridWriter()
    writer.SetFileName(str(path))
    writer.SetInputData(grid)
    if data.draw(st.booleans()):  # (not ASCII: VTK 9.6's ASCII writer crashes on its own cell-type arrays)
        writer.SetCompressorTypeToNone()
    writer.Write()
    raw = path.read_bytes()
    damage = data.draw(st.sampled_from(["none", "none", "cut", "overwrite"]))
    if damage == "cut":
        raw = raw[: data.draw(st.integers(0, len(raw) - 1))]
    elif damage == "overwrite":
        at = data.draw(st.integers(0, len(raw)))
        raw = raw[:at] + data.draw(st.binary(min_size=1, max_size=8)) + raw[at + 8:]
    path.write_bytes(raw)
    mesh = read_or_refuse("vtu", read_vtu, path)
    if mesh is not None:
        assert_finite(mesh.nodes)
        assert len(mesh.tets) and (mesh.volumes > 0).all()
        assert np.array_equal(np.unique(mesh.tets), np.arange(len(mesh.nodes)))
    if damage == "none" and defect != "none":
        assert mesh is None, f"a mesh with a defect ({defect}) was read"


NRRD_TYPES = {"uchar": np.uint8, "short": np.int16, "int": np.int32, "float": np.float32, "double": np.float64}


@st.composite
def nrrd_label_maps(draw):
    """A label map as an ASCII NRRD file written by hand, so that its header can be anything."""
    dimension = draw(st.sampled_from([3, 3, 3, 2]))
    sizes = draw(st.lists(st.integers(1, 5), min_size=dimension, max_size=dimension))
    kind = draw(st.sampled_from(list(NRRD_TYPES)))
    vector = draw(st.integers(1, 1) | st.integers(2, 3)) if draw(st.booleans()) else 1
    count = int(np.prod(sizes)) * vector
    value = st.sampled_from([0, 0, 1, 1, 2, 3, 4, 5, 6, 255, -1])
    if kind in ("float", "double"):
        value = value | st.sampled_from([0.5, math.nan, math.inf])
    values = draw(st.lists(value, min_size=count, max_size=count))
    spacing = draw(st.lists(st.sampled_from([1.0, 1.5, 0.0, -1.0, 1e-9, 1e6, math.nan, 3.0]),
                            min_size=dimension, max_size=dimension))
    if draw(st.booleans()):
        angle = draw(st.floats(0, 2 * math.pi))
        rotation = np.array([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0], [0, 0, 1]])
    else:
        rotation = np.eye(3)
    if draw(st.booleans()):
        rotation = rotation + np.array(draw(st.lists(st.sampled_from([0.0, 0.0, 0.3]), min_size=9,
                                                      max_size=9))).reshape(3, 3)
    rotation = rotation[:dimension, :dimension]
    directions = " ".join("(" + ",".join(f"{v:.9g}" for v in rotation[i] * spacing[i]) + ")" for i in range(dimension))
    header = ["NRRD0004", f"type: {kind}", f"dimension: {dimension + (vector > 1)}",
              f"space dimension: {dimension}",
              f"sizes: {' '.join(map(str, ([vector] if vector > 1 else []) + sizes))}",
              f"space directions: {'none ' if vector > 1 else ''}{directions}",
              f"space origin: ({','.join(['0'] * dimension)})", "encoding: ascii", "", ""]
    body = " ".join("nan" if isinstance(v, float) and math.isnan(v) else str(v) for v in values)
    return "\n".join(header) + body + "\n"


@FUZZ
@given(nrrd_label_maps())
def test_label_maps(tmp_path_factory, text):
    path = tmp_path_factory.getbasetemp() / "fuzz-labels.nrrd"
    path.write_text(text)
    image = read_or_refuse("label map", read_label_map, path)
    if image is not None:
        import SimpleITK as sitk

        values = sitk.GetArrayViewFromImage(image)
        assert image.GetDimension() == 3 and image.GetNumberOfComponentsPerPixel() == 1
        assert set(np.unique(values).tolist()) <= {0, 1, 2, 3, 4, 5}
        assert np.isfinite(image.GetSpacing()).all() and min(image.GetSpacing()) > 0
    image = read_or_refuse("image", read_image, path)
    if image is not None:
        import SimpleITK as sitk

        assert_finite(sitk.GetArrayViewFromImage(image), image.GetSpacing(), image.GetOrigin())


EVALUATION = {"index": 0, "phase": "cmaes", "z": [0.5, 0.25], "values": {"fat.E": 1000.0, "fat.nu": 0.45},
              "objective": -1.2, "nmi": 1.2, "ncc": 0.9, "landmark_mean_mm": 1.0, "landmark_max_mm": 2.0,
              "status": "completed", "iterations": 900, "seconds": 0.5, "surface_mm": float("nan")}


@FUZZ
@given(st.data())
def test_fit_evaluation_logs(tmp_path_factory, data):
    lines = [json.dumps(dict(EVALUATION, index=i, z=[0.1 * i, 0.2])) for i in range(3)]
    at = data.draw(st.integers(0, len(lines) - 1))
    lines[at] = mutated_text(data, json.loads(lines[at])).replace("\n", " ")
    text = "\n".join(lines) + "\n"
    if data.draw(st.booleans()):
        text = text[: data.draw(st.integers(0, len(text)))]  # a run killed mid-write
    path = _write(tmp_path_factory.getbasetemp() / "evaluations.jsonl", text)
    evaluations = read_or_refuse("evaluations", read_evaluations, path)
    if evaluations is not None:
        assert len(evaluations) <= 3
        for evaluation in evaluations:
            assert_finite(evaluation.z)


ROW = {"case": "case1", "model": "iso-homo", "optimiser": "cmaes", "nmi": 1.2, "objective": -1.2, "evaluations": 24,
       "failed": 1, "seconds": 30.0, "stopped": "budget", "landmark_errors": {"mean": 1.0, "max": 2.0},
       "materials": {"breast": {"E": 1000.0, "nu": 0.45, "eta": 0.0}}, "truth": {"fat": {"E": 1000.0, "nu": 0.45}},
       "in_family": True, "device": "cpu"}


@FUZZ
@given(st.data())
def test_study_rows(tmp_path_factory, data):
    folder = tmp_path_factory.mktemp("study")
    for name, text in (("case1", json.dumps(ROW)), ("case2", mutated_text(data, ROW))):
        (folder / name / "iso-homo-cmaes").mkdir(parents=True)
        (folder / name / "iso-homo-cmaes" / ROW_FILE).write_text(text)
    try:
        rows = read_study(folder)
    except InputError as error:
        assert str(folder / "case2") in str(error)
        _log("study", str(error))
        return
    assert len(rows) == 2
