"""Landmarks (LPS) <-> MRML markups point-list (fiducial) nodes (RAS)."""

from __future__ import annotations

import numpy as np

from BreastBiomechLib.landmarks import Landmarks
from BreastBiomechLib.mrml import frames


def landmarks_to_markups_node(landmarks: Landmarks, scene, name: str = "Landmarks", node=None,
                              locked: bool = True):
    """Put ``landmarks`` into a (new or emptied) point-list node; labels and descriptions kept."""
    if node is None:
        node = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", name)
        node.CreateDefaultDisplayNodes()
    node.RemoveAllControlPoints()
    was = node.StartModify()
    for label, description, ras in zip(landmarks.labels, landmarks.descriptions, frames.flip(landmarks.positions)):
        index = node.AddControlPoint(float(ras[0]), float(ras[1]), float(ras[2]), label)
        node.SetNthControlPointDescription(index, description)
        node.SetNthControlPointLocked(index, locked)
    node.EndModify(was)
    return node


def landmarks_from_markups_node(node) -> Landmarks:
    """The defined control points of a point-list node as landmarks (LPS mm; world coordinates,
    i.e. with any parent transform applied)."""
    if node is None:
        raise ValueError("no markups node given")
    positions, labels, descriptions = [], [], []
    for i in range(node.GetNumberOfControlPoints()):
        if not node.GetNthControlPointPositionStatus(i) == node.PositionDefined:
            continue
        ras = [0.0, 0.0, 0.0]
        node.GetNthControlPointPositionWorld(i, ras)
        positions.append(ras)
        labels.append(node.GetNthControlPointLabel(i) or f"P-{i + 1}")
        descriptions.append(node.GetNthControlPointDescription(i))
    return Landmarks(frames.flip(np.array(positions).reshape(-1, 3)), labels, descriptions)
