"""Seed points for the seeded segmentation steps, placed from a case's ground truth the way a
user would click them: well inside the structure (away from its border) and spread over it.

Points in LPS millimetres.
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from BreastBiomechLib import labels as lt
from BreastBiomechLib.landmarks import Landmarks


def farthest_points(candidates: np.ndarray, count: int, seed_points: np.ndarray) -> np.ndarray:
    """Greedy farthest-point choice of ``count`` rows of ``candidates`` (indices), spreading away
    from ``seed_points`` and from each other."""
    chosen = []
    dist = np.full(len(candidates), np.inf)
    for p in seed_points:
        dist = np.minimum(dist, np.linalg.norm(candidates - p, axis=1))
    for _ in range(min(count, len(candidates))):
        k = int(np.argmax(dist))
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(candidates - candidates[k], axis=1))
    return np.array(chosen, dtype=int)


def seed_points(labels: sitk.Image, tissue: int | str, count: int = 4) -> Landmarks:
    """``count`` points inside ``tissue`` of the label map: among the voxels at least half as deep
    inside it as its deepest voxel, spread by farthest-point sampling (deterministic).

    Raises ValueError when the label map has no voxel of that tissue."""
    t = lt.tissue(tissue)
    region = sitk.GetArrayViewFromImage(labels) == t.label
    if not region.any():
        raise ValueError(f"the label map has no {t.name} voxels to place seeds in")
    depth = ndimage.distance_transform_edt(region, sampling=labels.GetSpacing()[::-1])
    zyx = np.argwhere(depth >= 0.5 * depth.max())
    points = np.array([labels.TransformIndexToPhysicalPoint([int(i) for i in v[::-1]]) for v in zyx])
    deepest = points[np.argmax(depth[tuple(zyx.T)])]
    chosen = farthest_points(points, count - 1, deepest[None, :]) if count > 1 else np.zeros(0, int)
    positions = np.vstack([deepest[None, :], points[chosen]])
    names = [f"{t.name}-{i}" for i in range(1, len(positions) + 1)]
    return Landmarks(positions, names, [f"{t.name} seed"] * len(positions))
