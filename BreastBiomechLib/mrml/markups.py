"""Landmarks (LPS) <-> MRML markups point-list (fiducial) nodes, and rigid plates <-> markups plane
nodes (RAS)."""

from __future__ import annotations

import numpy as np

from BreastBiomechLib.landmarks import Landmarks
from BreastBiomechLib.mrml import frames
from BreastBiomechLib.solver.model import Plate


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


TRAVEL_ATTRIBUTE = "BreastBiomech.PlateTravelMm"  # plate motion along its normal, mm (> 0: into the tissue)


def plate_to_plane_node(plate: Plate, scene, node=None, size_mm: tuple[float, float] = (200.0, 200.0)):
    """Show a rigid plate as a (new or given) markups plane node at its starting position, its
    travel along the normal kept in the node's ``BreastBiomech.PlateTravelMm`` attribute. A
    frictionless plane acts only through its normal, so the travel is the whole of its motion."""
    if node is None:
        node = scene.AddNewNodeByClass("vtkMRMLMarkupsPlaneNode", plate.name)
        node.CreateDefaultDisplayNodes()
    was = node.StartModify()
    node.SetOriginWorld(*frames.flip(plate.point).tolist())
    node.SetNormalWorld(*frames.flip(plate.normal).tolist())
    node.SetSizeMode(node.SizeModeAbsolute)
    node.SetSize(float(size_mm[0]), float(size_mm[1]))
    node.SetAttribute(TRAVEL_ATTRIBUTE, repr(float(plate.displacement @ plate.normal)))
    node.EndModify(was)
    return node


def plate_from_plane_node(node, slave_nodes, towards=None) -> Plate:
    """The rigid plate a markups plane node shows (LPS mm; world coordinates). ``towards`` (LPS
    mm, e.g. the mesh centre) orients the normal to face the tissue whichever way the plane was
    drawn; the travel (``BreastBiomech.PlateTravelMm``, default 0) moves the plate along it."""
    if node is None or not node.IsA("vtkMRMLMarkupsPlaneNode"):
        raise ValueError("a plate must be a markups plane node")
    if not node.GetIsPlaneValid():
        raise ValueError(f"plate {node.GetName()!r} is not fully placed; place its plane in the views first")
    origin, normal = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
    node.GetOriginWorld(origin)
    node.GetNormalWorld(normal)
    point, normal = frames.flip(origin), frames.flip(normal)
    if towards is not None and (np.asarray(towards, float) - point) @ normal < 0:
        normal = -normal
    return Plate(point, normal, plate_travel(node) * normal / np.linalg.norm(normal), slave_nodes, node.GetName())


def plate_travel(node) -> float:
    """A plate plane node's travel along its normal (mm, > 0 into the tissue; 0 when not set)."""
    text = node.GetAttribute(TRAVEL_ATTRIBUTE) or "0"
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"plate {node.GetName()!r}: its travel {text!r} is not a number of millimetres") from None
