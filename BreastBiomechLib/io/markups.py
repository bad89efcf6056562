"""Landmarks as Slicer markups point-list files (``.mrk.json``, markups schema v1.0.3).

Files are written in the LPS coordinate system (Slicer's default for files since 4.11) and can be
dragged into Slicer as a point list. Reading accepts LPS or RAS files.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from BreastBiomechLib.errors import InputError, reading
from BreastBiomechLib.io.atomic import write_text_atomically
from BreastBiomechLib.landmarks import Landmarks

SCHEMA = (
    "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/"
    "Resources/Schema/markups-schema-v1.0.3.json#"
)
_LPS_TO_RAS = np.array([-1.0, -1.0, 1.0])


def write_markups(path: str | Path, landmarks: Landmarks, name: str = "Landmarks") -> Path:
    """Write ``landmarks`` (LPS, mm) as a Slicer point list ``.mrk.json`` file; returns the path."""
    path = Path(path)
    if not path.name.endswith(".mrk.json"):
        raise ValueError(f"{path}: Slicer reads point lists from files named *.mrk.json")
    points = [
        {
            "id": str(i + 1),
            "label": label,
            "description": description,
            "associatedNodeID": "",
            "position": [float(c) for c in pos],
            "orientation": [-1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0],
            "selected": True,
            "locked": True,
            "visibility": True,
            "positionStatus": "defined",
        }
        for i, (label, description, pos) in enumerate(
            zip(landmarks.labels, landmarks.descriptions, landmarks.positions)
        )
    ]
    document = {
        "@schema": SCHEMA,
        "markups": [
            {
                "type": "Fiducial",
                "coordinateSystem": "LPS",
                "coordinateUnits": "mm",
                "locked": False,
                "fixedNumberOfControlPoints": False,
                "labelFormat": "%N-%d",
                "lastUsedControlPointNumber": len(points),
                "controlPoints": points,
                "measurements": [],
            }
        ],
    }
    write_text_atomically(path, json.dumps(document, indent=2) + "\n")
    return path


def read_markups(path: str | Path) -> Landmarks:
    """Read the first point list of a ``.mrk.json`` file; positions returned in LPS mm. A file
    that is not one, or a point without three finite coordinates, raises
    :class:`~BreastBiomechLib.errors.InputError` naming the file and the point."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such markups file")
    remedy = "save the point list again from Slicer's Markups module (.mrk.json)"
    with reading(path, "Slicer markups .mrk.json file", remedy):
        document = json.loads(path.read_text())
        if not isinstance(document, dict) or not isinstance(document.get("markups"), list) or not document["markups"]:
            raise InputError(f"{path}: not a Slicer markups .mrk.json file (no \"markups\" list); {remedy}")
        markup = document["markups"][0]
        if not isinstance(markup, dict):
            raise InputError(f"{path}: markups[0] is not a markup object; {remedy}")
        system = markup.get("coordinateSystem", "LPS")
        if system not in ("LPS", "RAS"):
            raise InputError(f"{path}: unknown coordinateSystem {system!r} (expected LPS or RAS)")
        units = markup.get("coordinateUnits", "mm")
        if units != "mm":
            raise InputError(f"{path}: coordinates in {units!r}; only millimetres are supported")
        points = markup.get("controlPoints", [])
        if not isinstance(points, list) or not all(isinstance(p, dict) for p in points):
            raise InputError(f"{path}: controlPoints must be a list of point objects; {remedy}")
        points = [p for p in points if p.get("positionStatus", "defined") == "defined"]
        for i, point in enumerate(points):
            position = point.get("position")
            if (not isinstance(position, list) or len(position) != 3
                    or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in position)
                    or not np.isfinite(np.asarray(position, dtype=np.float64)).all()):
                raise InputError(f"{path}: control point {i + 1} ({point.get('label', 'unlabelled')!r}) has position "
                                 f"{position!r}; a position is three finite numbers (mm)")
        positions = np.array([p["position"] for p in points], dtype=np.float64).reshape(-1, 3)
        if system == "RAS":
            positions = positions * _LPS_TO_RAS
        labels = [str(p.get("label") or f"P-{i + 1}") for i, p in enumerate(points)]
        descriptions = [str(p.get("description", "")) for p in points]
        return Landmarks(positions, labels, descriptions)
