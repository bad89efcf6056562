"""Test helpers for images in oblique, anisotropic geometries (LPS mm)."""

from __future__ import annotations

import numpy as np


def oblique_direction() -> np.ndarray:
    """A non-identity, non-axis-aligned rotation (det +1)."""
    a, b = np.radians(30.0), np.radians(-20.0)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return rz @ rx


def make_image(array: np.ndarray, geometry):
    import SimpleITK as sitk

    image = sitk.GetImageFromArray(array, isVector=array.ndim == 4)
    origin, spacing, direction = geometry
    image.SetOrigin(origin)
    image.SetSpacing(spacing)
    image.SetDirection(direction)
    return image
