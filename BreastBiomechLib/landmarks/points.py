"""Named point landmarks (internal tissue features, skin fiducials, nipple).

Positions are in millimetres in ITK physical space (LPS), one row per landmark.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Landmarks:
    """Named landmarks: ``positions[i]`` (LPS, mm) is called ``labels[i]``."""

    positions: np.ndarray
    labels: list[str]
    descriptions: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.positions = np.asarray(self.positions, dtype=np.float64).reshape(-1, 3)
        self.labels = [str(s) for s in self.labels]
        if not self.descriptions:
            self.descriptions = [""] * len(self.labels)
        if len(self.labels) != len(self.positions) or len(self.descriptions) != len(self.labels):
            raise ValueError(
                f"landmarks need one label and one description per position: got "
                f"{len(self.positions)} positions, {len(self.labels)} labels, "
                f"{len(self.descriptions)} descriptions"
            )
        if len(set(self.labels)) != len(self.labels):
            raise ValueError(f"landmark labels must be unique, got {self.labels}")
        if not np.all(np.isfinite(self.positions)):
            raise ValueError("landmark positions contain NaN or infinity")

    def __len__(self) -> int:
        return len(self.labels)

    def position(self, label: str) -> np.ndarray:
        """Position (LPS, mm) of the landmark called ``label``."""
        try:
            return self.positions[self.labels.index(label)]
        except ValueError:
            raise KeyError(f"no landmark {label!r}; have {self.labels}") from None
