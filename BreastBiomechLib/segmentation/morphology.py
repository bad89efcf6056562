"""Small helpers on voxel masks with anisotropic spacing: balls, components, local means.

Arrays in SimpleITK's (z, y, x) order; lengths in millimetres.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def ball(spacing_zyx, radius_mm: float) -> np.ndarray:
    """A structuring element: the voxel offsets within ``radius_mm`` of the centre, plus the six
    face neighbours (so that it grows a mask by at least one voxel along thick-slice axes)."""
    spacing = np.asarray(spacing_zyx, dtype=float)
    r = np.maximum(1, np.floor(radius_mm / spacing)).astype(int)
    z, y, x = np.ogrid[-r[0]:r[0] + 1, -r[1]:r[1] + 1, -r[2]:r[2] + 1]
    distance = np.sqrt((z * spacing[0]) ** 2 + (y * spacing[1]) ** 2 + (x * spacing[2]) ** 2)
    face = (np.abs(z) + np.abs(y) + np.abs(x)) <= 1
    return (distance <= radius_mm) | face


def largest_component(mask: np.ndarray) -> np.ndarray:
    """The largest 6-connected component of ``mask`` (empty if the mask is)."""
    labels, count = ndimage.label(mask)
    if count == 0:
        return np.zeros_like(mask, dtype=bool)
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return labels == int(np.argmax(sizes))


def seeded_components(mask: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """The 6-connected components of ``mask`` that hold one of the ``seeds`` (N, 3) voxels."""
    labels, _ = ndimage.label(mask)
    keep = np.unique(labels[tuple(np.asarray(seeds).T)])
    return np.isin(labels, keep[keep > 0])


def local_mean(values: np.ndarray, weights: np.ndarray, sigma_vox) -> np.ndarray:
    """Gaussian-weighted local mean of ``values`` over the voxels where ``weights`` > 0
    (normalised convolution); where no weighted voxel is near, the result is 0."""
    num = ndimage.gaussian_filter(values * weights, sigma_vox, mode="nearest")
    den = ndimage.gaussian_filter(weights.astype(np.float32), sigma_vox, mode="nearest")
    return np.where(den > 1e-3, num / np.maximum(den, 1e-3), 0.0).astype(np.float32)
