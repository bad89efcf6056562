"""Named point landmarks (:class:`Landmarks`), their motion through an FE displacement
(:func:`map_landmarks`) and their errors against measured positions (:func:`landmark_errors`).
Positions in LPS millimetres."""

from BreastBiomechLib.landmarks.mapping import (LandmarkErrors, LandmarkMapper, PointLocation, landmark_errors,
                                                locate_points, map_landmarks)
from BreastBiomechLib.landmarks.points import Landmarks

__all__ = ["LandmarkErrors", "LandmarkMapper", "Landmarks", "PointLocation", "landmark_errors", "locate_points", "map_landmarks"]
