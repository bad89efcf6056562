"""Slice views set up for a comparison: volumes side by side in the same plane, linked.

Slicer applies a layout's default orientations only to the slice views it creates
(vtkMRMLLayoutLogic): switching to the side-by-side layout keeps an existing Yellow view in its
sagittal plane, so a comparison would show the measured residual axial and the predicted one
sagittal. Here each view's plane is set explicitly and the views are linked (a slice moved in
one moves in the other)."""

from __future__ import annotations


def compare_side_by_side(views, background_id: str, foreground_ids, opacity: float = 0.7) -> str:
    """Show ``background_id`` under each of ``foreground_ids`` (one per view, None: none) in
    ``views`` ((slice node, slice composite node) pairs), every view in the first view's
    orientation (e.g. "Axial") and all linked. Returns that orientation."""
    views, foreground_ids = list(views), list(foreground_ids)
    if len(views) != len(foreground_ids):
        raise ValueError(f"{len(views)} views for {len(foreground_ids)} foreground volumes")
    orientation = views[0][0].GetOrientationString()
    for (slice_node, composite), foreground in zip(views, foreground_ids):
        if slice_node.GetOrientationString() != orientation and not slice_node.SetOrientation(orientation):
            raise ValueError(f"the {slice_node.GetLayoutName()} view cannot take the {orientation} orientation")
        composite.SetBackgroundVolumeID(background_id)
        composite.SetForegroundVolumeID(foreground)
        composite.SetForegroundOpacity(opacity)
        composite.SetLinkedControl(True)
    return orientation
