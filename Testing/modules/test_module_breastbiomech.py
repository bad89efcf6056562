"""The BreastBiomech home module's Logic against a real MRML scene (slicer-core, headless)."""

from __future__ import annotations

import os

import numpy as np
import pytest
import SimpleITK as sitk
import vtk

pytest.importorskip("slicer")
import BreastBiomech  # noqa: E402  (BreastBiomech/ is on the test path)
from BreastBiomechLib import labels as lt  # noqa: E402
from BreastBiomechLib.phantom import PhantomParameters, generate_phantom, write_phantom  # noqa: E402

pytestmark = pytest.mark.mrml

SMALL = PhantomParameters(seed=5, volume_cm3=430.0, density=0.3, tumour_diameter_mm=10.0,
                          spacing_mm=(1.5, 1.5, 2.5))


@pytest.fixture(scope="module")
def case():
    return generate_phantom(SMALL)


def test_module_classes_importable_headless():
    assert not BreastBiomech.IN_SLICER_APPLICATION
    assert BreastBiomech.BreastBiomechLogic.MODULE_NAME == "BreastBiomech"
    with pytest.raises(RuntimeError, match="needs the Slicer application"):
        BreastBiomech.BreastBiomechWidget()


def test_case_into_scene_keeps_geometry_labels_and_landmarks(scene, case):
    logic = BreastBiomech.BreastBiomechLogic(scene)
    nodes = logic.addCaseToScene(case, "Phantom")

    # MR volume: a voxel's RAS position is its LPS position flipped
    volume = nodes["volume"]
    ijk_to_ras = vtk.vtkMatrix4x4()
    volume.GetIJKToRASMatrix(ijk_to_ras)
    for ijk in [(0, 0, 0), (17, 40, 9)]:
        lps = np.array(case.image.TransformIndexToPhysicalPoint(ijk))
        np.testing.assert_allclose(ijk_to_ras.MultiplyPoint([*ijk, 1])[:3], lps * [-1, -1, 1], atol=1e-9)
    assert volume.GetImageData().GetDimensions() == case.image.GetSize()

    # segmentation: one segment per tissue, named and coloured from the label table, exact voxels
    segmentation = nodes["segmentation"].GetSegmentation()
    names = {segmentation.GetNthSegment(i).GetName() for i in range(segmentation.GetNumberOfSegments())}
    assert names == {"fat", "glandular", "muscle", "tumour"}
    from BreastBiomechLib import mrml

    back = mrml.labels_from_segmentation_node(nodes["segmentation"], scene, reference=case.labels)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(back), sitk.GetArrayFromImage(case.labels))

    # fractions and landmarks
    assert set(nodes["fractions"]) == set(case.fractions)
    landmarks = nodes["landmarks"]
    assert landmarks.GetNumberOfControlPoints() == 17
    index = landmarks.GetControlPointIndexByLabel("nipple")
    ras = [0.0, 0.0, 0.0]
    landmarks.GetNthControlPointPosition(index, ras)
    np.testing.assert_allclose(ras, case.landmarks.position("nipple") * [-1, -1, 1], atol=1e-9)

    # seed point lists for the Breast Segmentation module sit inside their tissues
    assert set(nodes["seeds"]) == {"muscle", "tumour"}
    for tissue, node in nodes["seeds"].items():
        points = mrml.landmarks_from_markups_node(node).positions
        assert len(points) >= 3
        index = [case.labels.TransformPhysicalPointToIndex(tuple(p)) for p in points]
        assert all(case.labels[i] == lt.tissue(tissue).label for i in index)

    # the parameter node points at the results
    parameters = logic.getParameterNode()
    assert parameters.reference("mrVolume") is volume
    assert parameters.reference("segmentation") is nodes["segmentation"]
    assert parameters.reference("landmarks") is landmarks


def test_parameter_node_drives_the_phantom_parameters(scene):
    logic = BreastBiomech.BreastBiomechLogic(scene)
    parameters = logic.getParameterNode()
    assert logic.phantomParameters(parameters).volume_cm3 == 800.0
    logic.applyCasePreset(parameters, 1)
    p = logic.phantomParameters(parameters)
    assert (p.volume_cm3, p.tumour_diameter_mm, p.seed) == (1364.0, 18.0, 101)
    parameters["density"] = 0.4
    parameters["skinSeparate"] = True
    p = logic.phantomParameters(parameters)
    assert p.density == 0.4 and p.skin_separate
    parameters["volumeCm3"] = 50.0
    with pytest.raises(ValueError, match="volume_cm3"):
        logic.phantomParameters(parameters)


def test_load_generated_phantom_and_case_folder(scene, case, tmp_path):
    logic = BreastBiomech.BreastBiomechLogic(scene)
    messages = []
    params = PhantomParameters(seed=9, volume_cm3=420.0, density=0.2, spacing_mm=(2.0, 2.0, 3.0))
    nodes = logic.loadPhantom(params, progress=lambda f, m: messages.append((f, m)))
    assert messages[0][0] == 0.0 and messages[-1] == (1.0, "done")
    assert nodes["summary"]["breast_volume_cm3"] == pytest.approx(420.0, rel=0.03)
    write_phantom(case, tmp_path / "case", overview=False)
    loaded = logic.loadPhantomFolder(str(tmp_path / "case"))
    assert loaded["volume"].GetName() == "case_MR"
    assert loaded["segmentation"].GetSegmentation().GetSegment(lt.TUMOUR.name) is not None
    with pytest.raises(ValueError, match="choose a phantom case folder"):
        logic.loadPhantomFolder("")
    for empty in (".", "./"):  # what an empty path field can read; never the working directory
        with pytest.raises(ValueError, match="choose a phantom case folder"):
            logic.loadPhantomFolder(empty)
    with pytest.raises(FileNotFoundError, match="not a phantom case folder"):
        logic.loadPhantomFolder(str(tmp_path))


def test_breast_phantom_sample_loads_from_a_script_with_slicers_readers(scene, tmp_path):
    """``SampleData.downloadSample("Breast phantom")`` fetches each URI with urllib into the cache
    (checking its SHA-256) and loads it with the file type's reader: the same steps here with
    slicer-core's storage nodes."""
    import hashlib
    import urllib.request

    import slicer

    args = BreastBiomech.sampleDataArguments()
    count = len(args["uris"])
    assert count == 3 and all(len(args[key]) == count for key in ("fileNames", "nodeNames", "loadFileType", "checksums"))
    assert args["sampleName"] == BreastBiomech.SAMPLE_NAME and os.path.isfile(args["thumbnailFileName"])
    readers = {"VolumeFile": ("vtkMRMLScalarVolumeNode", "vtkMRMLVolumeArchetypeStorageNode"),
               "SegmentationFile": ("vtkMRMLSegmentationNode", "vtkMRMLSegmentationStorageNode"),
               "MarkupsFile": ("vtkMRMLMarkupsFiducialNode", "vtkMRMLMarkupsJsonStorageNode")}
    nodes = []
    for uri, name, node_name, kind, checksum in zip(args["uris"], args["fileNames"], args["nodeNames"],
                                                    args["loadFileType"], args["checksums"]):
        assert uri.startswith("file://")
        fetched = tmp_path / name
        urllib.request.urlretrieve(uri, fetched)
        assert checksum == "SHA256:" + hashlib.sha256(fetched.read_bytes()).hexdigest()
        node_class, storage_class = readers[kind]
        node = scene.AddNewNodeByClass(node_class, node_name)
        storage = scene.AddNode(getattr(slicer, storage_class)())  # headless, not every reader is registered
        storage.SetFileName(str(fetched))
        assert storage.ReadData(node), f"{name} did not load as a {kind}"
        nodes.append(node)
    volume, segmentation, landmarks = nodes
    assert volume.GetImageData().GetDimensions()[0] > 50
    assert slicer.util.arrayFromVolume(volume).max() > 100  # the signal x 1000 as uint16
    names = {segmentation.GetSegmentation().GetNthSegment(i).GetName()
             for i in range(segmentation.GetSegmentation().GetNumberOfSegments())}
    assert {"fat", "glandular", "muscle"} <= names
    assert landmarks.GetNumberOfControlPoints() == 17


def test_shipped_sample_is_what_the_generator_makes(scene, tmp_path):
    shipped = BreastBiomech.sampleDataArguments()["uris"]
    made = BreastBiomech.BreastBiomechLogic(scene).writeSampleData(str(tmp_path))
    paths = [urllib_path(uri) for uri in shipped]
    mr_shipped, mr_made = (sitk.GetArrayFromImage(sitk.ReadImage(str(p))).astype(int) for p in (paths[0], made[0]))
    assert mr_shipped.shape == mr_made.shape and np.mean(np.abs(mr_shipped - mr_made) <= 1) > 0.999
    seg_shipped, seg_made = (sitk.GetArrayFromImage(sitk.ReadImage(str(p))) for p in (paths[1], made[1]))
    assert seg_shipped.shape == seg_made.shape and np.mean(seg_shipped == seg_made) > 0.999
    from BreastBiomechLib.io.markups import read_markups

    a, b = read_markups(paths[2]), read_markups(made[2])
    assert a.labels == b.labels
    np.testing.assert_allclose(a.positions, b.positions, atol=0.05)


def urllib_path(uri: str) -> str:
    import urllib.parse
    import urllib.request

    return urllib.request.url2pathname(urllib.parse.urlparse(uri).path)
