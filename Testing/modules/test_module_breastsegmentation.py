"""The BreastSegmentation module's Logic against a real MRML scene (slicer-core, headless).

Inputs go in as the nodes a user has (a scalar volume, point lists in RAS) and the outputs are
read back through the segmentation node and compared with the phantom's ground truth, so a lost
RAS/LPS flip, a segment written under the wrong name or an edit that a later step ignores shows
up here."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

pytest.importorskip("slicer")
import BreastSegmentation  # noqa: E402  (BreastBiomech/ is on the test path)

from BreastBiomechLib import labels as lt  # noqa: E402
from BreastBiomechLib.mrml import (  # noqa: E402
    image_from_volume_node,
    image_to_volume_node,
    labels_from_segmentation_node,
    landmarks_to_markups_node,
    mask_from_segment,
    mask_to_segment,
)
from BreastBiomechLib.phantom import PhantomParameters, generate_phantom  # noqa: E402
from BreastBiomechLib.phantom.seeds import seed_points  # noqa: E402
from BreastBiomechLib.segmentation import dice_per_tissue  # noqa: E402

pytestmark = pytest.mark.mrml


@pytest.fixture(scope="module")
def case():
    return generate_phantom(PhantomParameters(seed=5, volume_cm3=450.0, tumour_diameter_mm=15.0))


def _set_up(scene, case, tumour=True):
    logic = BreastSegmentation.BreastSegmentationLogic(scene)
    p = logic.getParameterNode()
    p.set_reference("inputVolume", image_to_volume_node(case.image, scene, "MR"))
    p.set_reference("muscleSeeds", landmarks_to_markups_node(seed_points(case.labels, "muscle", 4), scene, "Muscle"))
    if tumour:
        p.set_reference("tumourSeeds", landmarks_to_markups_node(seed_points(case.labels, "tumour", 3), scene, "Tumour"))
    return logic, p


def test_all_steps_fill_the_segmentation_probabilities_and_tables(scene, case):
    logic, p = _set_up(scene, case)
    stages = []
    text = logic.runAll(p, progress=lambda fraction, message: stages.append(fraction))
    assert stages == sorted(stages) and stages[-1] == 1.0
    assert "glandular density" in text

    node = p.reference("outputSegmentation")
    assert node.GetName() == "MR_tissues"
    segmentation = node.GetSegmentation()
    segments = {segmentation.GetNthSegment(i).GetName(): segmentation.GetNthSegment(i).GetColor()
                for i in range(segmentation.GetNumberOfSegments())}
    assert set(segments) == {"fat", "glandular", "muscle", "tumour"}
    assert segments["glandular"] == pytest.approx(lt.GLANDULAR.color)
    labels = labels_from_segmentation_node(node, scene, reference=case.image)
    dice = dice_per_tissue(labels, case.labels)
    assert min(dice.values()) >= 0.85, dice

    # probability volumes on the MR grid, at most 1 in sum; the bias field; the volumes table
    total = 0
    for tissue in ("fat", "glandular", "muscle", "tumour"):
        volume = p.reference(logic.PROBABILITY_ROLES[tissue])
        assert volume.GetName() == f"MR_p_{tissue}"
        image = image_from_volume_node(volume)
        assert image.GetSize() == case.image.GetSize()
        np.testing.assert_allclose(image.GetOrigin(), case.image.GetOrigin(), atol=1e-6)
        total = total + sitk.GetArrayFromImage(image)
    assert total.max() <= 1 + 1e-5
    bias = sitk.GetArrayFromImage(image_from_volume_node(p.reference("biasField")))
    assert 0.5 < bias.min() and bias.max() < 1.5
    table = p.reference("volumesTable").GetTable()
    rows = {table.GetValue(r, 0).ToString(): table.GetValue(r, 1).ToDouble() for r in range(table.GetNumberOfRows())}
    truth = case.summary["tissue_volumes_cm3"]
    assert rows["glandular"] == pytest.approx(truth["glandular"], rel=0.05)

    # a second run refills the same nodes
    count = scene.GetNumberOfNodes()
    logic.runAll(p)
    assert scene.GetNumberOfNodes() == count
    assert p.reference("outputSegmentation") is node


def test_steps_read_the_segments_as_edited(scene, case):
    logic, p = _set_up(scene, case)
    with pytest.raises(ValueError, match="segment the pectoral muscle first"):
        logic.classifyTissues(p)
    logic.segmentMuscle(p)
    node = p.reference("outputSegmentation")
    assert node.GetSegmentation().GetNumberOfSegments() == 1
    muscle = mask_from_segment(node, "muscle", scene, case.image)
    truth = sitk.GetArrayFromImage(case.labels) == lt.MUSCLE.label
    grown = sitk.GetArrayFromImage(muscle).astype(bool)
    assert 2 * np.count_nonzero(grown & truth) / (grown.sum() + truth.sum()) > 0.9

    # the user erases the lowest slices of the muscle in the Segment Editor; later steps keep the edit
    edited = sitk.GetArrayFromImage(muscle)
    edited[:3] = 0
    edited_image = sitk.GetImageFromArray(edited)
    edited_image.CopyInformation(case.image)
    mask_to_segment(edited_image, node, "muscle", scene)

    text = logic.segmentTumour(p)
    assert "equivalent diameter" in text
    logic.classifyTissues(p)
    labels = sitk.GetArrayFromImage(labels_from_segmentation_node(node, scene, reference=case.image))
    np.testing.assert_array_equal(labels == lt.MUSCLE.label, edited.astype(bool))
    dice = dice_per_tissue(labels_from_segmentation_node(node, scene, reference=case.image), case.labels)
    assert dice["tumour"] >= 0.85 and dice["glandular"] >= 0.85


def test_the_fascia_option_reaches_the_library(scene, case):
    """The panel's "Give tissue lying on the muscle back to the breast" (on by default, saved in
    the parameter node) switches the library's fascia step."""
    logic, p = _set_up(scene, case)
    assert p["tissueOnFascia"] is True
    assert logic.settings(p).fascia is not None
    p["tissueOnFascia"] = False
    assert logic.settings(p).fascia is None
    assert p.node.GetParameter("tissueOnFascia") == "False"


def test_the_fraction_smoothing_reaches_the_library(scene, case):
    """The panel's "Fraction smoothing" (0.2 by default, as the library's and the command line's)
    sets the EM's final neighbour average of the glandular fraction; 0 switches it off."""
    logic, p = _set_up(scene, case)
    assert logic.settings(p).em.fraction_smoothing == 0.2
    p["fractionSmoothing"] = 0.0
    assert logic.settings(p).em.fraction_smoothing == 0.0
    assert float(p.node.GetParameter("fractionSmoothing")) == 0.0


def test_missing_inputs_are_named(scene, case):
    logic, p = _set_up(scene, case, tumour=False)
    with pytest.raises(ValueError, match="tumour"):
        logic.segmentTumour(p)
    p.set_reference("muscleSeeds", None)
    with pytest.raises(ValueError, match="seeds on the pectoral muscle"):
        logic.runAll(p)
    empty = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "Empty")
    p.set_reference("muscleSeeds", empty)
    with pytest.raises(ValueError, match="no placed points"):
        logic.segmentMuscle(p)
    p.set_reference("inputVolume", None)
    with pytest.raises(ValueError, match="choose the MR volume"):
        logic.segmentMuscle(p)


def test_a_cancelled_step_leaves_the_scene_as_it_was(scene, case):
    """The panel's Cancel answers False to the progress callback: the step stops with
    StepCancelled and writes nothing (the panel keeps its other steps disabled meanwhile)."""
    logic, p = _set_up(scene, case)
    with pytest.raises(BreastSegmentation.StepCancelled, match="Pectoral muscle segmentation cancelled at 0 %"):
        logic.segmentMuscle(p, progress=lambda fraction, message: False)
    assert p.reference("outputSegmentation") is None
    logic.segmentMuscle(p)
    segmentation = p.reference("outputSegmentation").GetSegmentation()
    before = [segmentation.GetNthSegmentID(i) for i in range(segmentation.GetNumberOfSegments())]
    calls = []

    def cancel_on_third(fraction, message):
        calls.append(message)
        return len(calls) < 3

    with pytest.raises(BreastSegmentation.StepCancelled, match="Segmentation cancelled"):
        logic.runAll(p, progress=cancel_on_third)
    assert len(calls) == 3
    assert [segmentation.GetNthSegmentID(i) for i in range(segmentation.GetNumberOfSegments())] == before
    assert p.reference("volumesTable") is None
