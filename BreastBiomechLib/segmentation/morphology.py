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


def smooth_trend(values: np.ndarray, weights: np.ndarray, sigma_mm: float, spacing_zyx) -> np.ndarray:
    """:func:`local_mean` for long scales, computed on a grid coarsened to about a third of
    ``sigma_mm`` and interpolated back (linear): a trend this smooth loses nothing, and the
    filters run on a small fraction of the voxels. 0 where no weighted voxel is near."""
    spacing = np.asarray(spacing_zyx, dtype=float)
    factors = np.maximum(1, np.floor(sigma_mm / (3 * spacing))).astype(int)
    if np.all(factors == 1):
        return local_mean(values, weights, sigma_mm / spacing)
    shape = np.asarray(values.shape)
    padded = -(-shape // factors) * factors
    pad = [(0, int(p - s)) for p, s in zip(padded, shape)]
    w = np.pad(weights.astype(np.float32), pad)
    v = np.pad(values.astype(np.float32), pad, mode="edge") * w
    blocks = [(int(n // f), int(f)) for n, f in zip(padded, factors)]
    shape6 = [d for pair in blocks for d in pair]
    coarse_w = w.reshape(shape6).sum(axis=(1, 3, 5))
    coarse_v = v.reshape(shape6).sum(axis=(1, 3, 5))
    sigma = sigma_mm / (spacing * factors)
    num = ndimage.gaussian_filter(coarse_v, sigma, mode="nearest")
    den = ndimage.gaussian_filter(coarse_w, sigma, mode="nearest")
    coarse = np.where(den > 1e-3 * factors.prod(), num / np.maximum(den, 1e-12), np.nan)
    valid = ~np.isnan(coarse)
    filled = _upsample_linear(np.where(valid, coarse, 0.0), factors, shape)
    support = _upsample_linear(valid.astype(np.float64), factors, shape)
    return np.where(support > 0.99, filled, 0.0).astype(np.float32)


def _upsample_linear(coarse: np.ndarray, factors, shape) -> np.ndarray:
    """Separable linear interpolation of block means (block centres at (f - 1) / 2 fine voxels)
    onto the fine grid of ``shape``; constant beyond the outermost centres."""
    out = coarse
    for axis, (n, f) in enumerate(zip(shape, factors)):
        position = np.clip((np.arange(n) - (f - 1) / 2) / f, 0, out.shape[axis] - 1)
        i0 = np.floor(position).astype(int)
        i1 = np.minimum(i0 + 1, out.shape[axis] - 1)
        view = [None] * out.ndim
        view[axis] = slice(None)
        w = (position - i0)[tuple(view)]
        out = out.take(i0, axis=axis) * (1 - w) + out.take(i1, axis=axis) * w
    return out
