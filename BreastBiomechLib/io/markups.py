"""Landmarks as Slicer markups point-list files (``.mrk.json``, markups schema v1.0.3).

Files are written in the LPS coordinate system (Slicer's default for files since 4.11) and can be
dragged into Slicer as a point list. Reading accepts LPS or RAS files.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

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
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(document, indent=2) + "\n")
    return path


def read_markups(path: str | Path) -> Landmarks:
    """Read the first point list of a ``.mrk.json`` file; positions returned in LPS mm."""
    path = Path(path)
    try:
        document = json.loads(path.read_text())
        markup = document["markups"][0]
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such markups file") from None
    except (json.JSONDecodeError, KeyError, IndexError, TypeError) as exc:
        raise ValueError(f"{path}: not a Slicer markups .mrk.json file ({exc})") from None
    system = markup.get("coordinateSystem", "LPS")
    if system not in ("LPS", "RAS"):
        raise ValueError(f"{path}: unknown coordinateSystem {system!r} (expected LPS or RAS)")
    units = markup.get("coordinateUnits", "mm")
    if units != "mm":
        raise ValueError(f"{path}: coordinates in {units!r}; only millimetres are supported")
    points = [p for p in markup.get("controlPoints", []) if p.get("positionStatus", "defined") == "defined"]
    positions = np.array([p["position"] for p in points], dtype=np.float64).reshape(-1, 3)
    if system == "RAS":
        positions = positions * _LPS_TO_RAS
    labels = [p.get("label") or f"P-{i + 1}" for i, p in enumerate(points)]
    descriptions = [p.get("description", "") for p in points]
    return Landmarks(positions, labels, descriptions)
