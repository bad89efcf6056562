"""Label images (LPS) <-> MRML segmentation nodes, one segment per tissue of the label table."""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
import slicer
import vtk

from BreastBiomechLib import labels as lt
from BreastBiomechLib.mrml.volumes import image_from_volume_node, image_to_volume_node


def register_segmentation_converters() -> None:
    """Register the labelmap <-> closed-surface converter rules (the Slicer application does this
    at start-up; headless scenes need it once per process). Idempotent."""
    factory = slicer.vtkSegmentationConverterFactory.GetInstance()
    have = {rule.GetName() for rule in factory.GetConverterRules()}
    rules = [slicer.vtkBinaryLabelmapToClosedSurfaceConversionRule(),
             slicer.vtkClosedSurfaceToBinaryLabelmapConversionRule()]
    for rule in rules:
        if rule.GetName() not in have:
            factory.RegisterConverterRule(rule)


def labels_to_segmentation_node(label_image: sitk.Image, scene, name: str = "Tissues", node=None,
                                closed_surface: bool = False):
    """Make (or refill) a segmentation node with one segment per tissue present in ``label_image``.

    Segment IDs and names are the tissue names of :mod:`BreastBiomechLib.labels`, colours its
    colours. Unknown label values are an error. ``closed_surface`` also builds the closed-surface
    representation (for 3D display and for meshing)."""
    values = np.unique(sitk.GetArrayViewFromImage(label_image))
    unknown = sorted(set(int(v) for v in values) - {lt.BACKGROUND} - set(lt.BY_LABEL))
    if unknown:
        raise ValueError(f"label values {unknown} are not in the tissue label table "
                         f"({', '.join(f'{t.label}={t.name}' for t in lt.TISSUES)})")
    return named_labels_to_segmentation_node(label_image, {t.label: (t.name, t.color) for t in lt.TISSUES}, scene,
                                             name, node, closed_surface)


def named_labels_to_segmentation_node(label_image: sitk.Image, segments: dict[int, tuple[str, tuple]], scene,
                                      name: str, node=None, closed_surface: bool = False):
    """Make (or refill) a segmentation node with one segment per value of ``segments`` ({label
    value: (name, RGB colour 0-1)}) present in ``label_image`` (LPS); other values are background.
    Segment IDs are the names."""
    values = np.unique(sitk.GetArrayViewFromImage(label_image))
    register_segmentation_converters()
    if node is None:
        node = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", name)
        node.CreateDefaultDisplayNodes()
    segmentation = node.GetSegmentation()
    segmentation.RemoveAllSegments()
    labelmap = image_to_volume_node(sitk.Cast(label_image, sitk.sitkUInt8), scene, name + "_import",
                                    labelmap=True, display=False)
    try:
        node.SetReferenceImageGeometryParameterFromVolumeNode(labelmap)
        updated = vtk.vtkStringArray()
        for value in range(1, int(values.max()) + 1 if values.size else 1):
            if value in segments and value in values:
                segment_name, colour = segments[value]
                segmentation.AddEmptySegment(segment_name, segment_name, list(colour))
                updated.InsertNextValue(segment_name)
            else:
                updated.InsertNextValue("")
        if updated.GetNumberOfValues() and not slicer.vtkSlicerSegmentationsModuleLogic.ImportLabelmapToSegmentationNode(
                labelmap, node, updated):
            raise RuntimeError("Slicer could not import the label map into the segmentation node")
    finally:
        scene.RemoveNode(labelmap)
    if closed_surface:
        node.CreateClosedSurfaceRepresentation()
    return node


def labels_from_segmentation_node(node, scene, reference: sitk.Image | None = None) -> sitk.Image:
    """The segmentation as a label image (uint8, label-table values from the segment names).

    With ``reference`` the label image has exactly its grid (LPS); otherwise the segmentation's
    own reference geometry. Segment names must be tissue names of the label table; where
    segments overlap, the later segment wins."""
    segmentation = node.GetSegmentation()
    ids = [segmentation.GetNthSegmentID(i) for i in range(segmentation.GetNumberOfSegments())]
    names = [segmentation.GetSegment(i).GetName() for i in ids]
    unknown = [n for n in names if n not in lt.BY_NAME]
    if unknown:
        raise ValueError(f"segments {unknown} are not tissues of the label table; rename them to one of "
                         f"{[t.name for t in lt.TISSUES]}")
    exported = _export_segments(node, ids, scene, reference)
    # exported values are 1..n in the order of ``ids``; map them to the table's values
    lookup = np.zeros(len(ids) + 1, dtype=np.uint8)
    for k, n in enumerate(names, start=1):
        lookup[k] = lt.BY_NAME[n].label
    out = sitk.GetImageFromArray(lookup[sitk.GetArrayViewFromImage(exported).astype(np.int64)])
    out.CopyInformation(exported)
    return out


def mask_from_segment(node, tissue_name: str, scene, reference: sitk.Image) -> sitk.Image | None:
    """The segment named ``tissue_name`` alone as a uint8 mask (1 inside) on ``reference``'s grid
    (LPS), other segments ignored even where they overlap it; None if there is no such segment."""
    segmentation = node.GetSegmentation()
    ids = [segmentation.GetNthSegmentID(i) for i in range(segmentation.GetNumberOfSegments())]
    match = [i for i in ids if segmentation.GetSegment(i).GetName() == tissue_name]
    if not match:
        return None
    exported = _export_segments(node, match[:1], scene, reference)
    return sitk.Cast(exported != 0, sitk.sitkUInt8)


def mask_to_segment(mask: sitk.Image, node, tissue_name: str, scene) -> str:
    """Fill the segment of ``node`` named ``tissue_name`` (made if missing, with the label table's
    colour) with the non-zero voxels of ``mask`` (LPS); other segments are left as they are.
    Returns the segment's ID."""
    tissue = lt.tissue(tissue_name)
    register_segmentation_converters()
    segmentation = node.GetSegmentation()
    ids = [segmentation.GetNthSegmentID(i) for i in range(segmentation.GetNumberOfSegments())]
    match = [i for i in ids if segmentation.GetSegment(i).GetName() == tissue.name]
    segment_id = match[0] if match else segmentation.AddEmptySegment(tissue.name, tissue.name, list(tissue.color))
    labelmap = image_to_volume_node(sitk.Cast(mask != 0, sitk.sitkUInt8), scene, tissue.name + "_import",
                                    labelmap=True, display=False)
    try:
        if not ids:
            node.SetReferenceImageGeometryParameterFromVolumeNode(labelmap)
        updated = vtk.vtkStringArray()
        updated.InsertNextValue(segment_id)
        if not slicer.vtkSlicerSegmentationsModuleLogic.ImportLabelmapToSegmentationNode(labelmap, node, updated):
            raise RuntimeError(f"Slicer could not import the {tissue.name} mask into the segmentation node")
    finally:
        scene.RemoveNode(labelmap)
    return segment_id


def _export_segments(node, ids: list[str], scene, reference: sitk.Image | None) -> sitk.Image:
    """The segments ``ids`` as one label image, values 1..n in the order of ``ids`` (LPS)."""
    register_segmentation_converters()
    colours_before = {scene.GetNthNodeByClass(i, "vtkMRMLColorTableNode").GetID()
                      for i in range(scene.GetNumberOfNodesByClass("vtkMRMLColorTableNode"))}
    labelmap = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode", "export")
    reference_node = None
    try:
        if reference is not None:
            blank = sitk.Image(reference.GetSize(), sitk.sitkUInt8)
            blank.CopyInformation(reference)
            reference_node = image_to_volume_node(blank, scene, "reference", display=False)
        id_array = vtk.vtkStringArray()
        for i in ids:
            id_array.InsertNextValue(i)
        extent_mode = slicer.vtkSegmentation.EXTENT_REFERENCE_GEOMETRY
        ok = slicer.vtkSlicerSegmentationsModuleLogic.ExportSegmentsToLabelmapNode(
            node, id_array, labelmap, reference_node, extent_mode)
        if not ok:
            raise RuntimeError("Slicer could not export the segmentation to a label map")
        return image_from_volume_node(labelmap)
    finally:
        display = labelmap.GetDisplayNode()
        colours = display.GetColorNode() if display is not None else None
        scene.RemoveNode(labelmap)
        if colours is not None and colours.GetID() not in colours_before:  # made by the export: not the user's
            scene.RemoveNode(colours)
        if reference_node is not None:
            scene.RemoveNode(reference_node)
