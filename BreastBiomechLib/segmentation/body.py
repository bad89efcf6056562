"""The body (everything that is not air) in an MR volume, robust to bias field and noise.

Arrays in SimpleITK's (z, y, x) order; lengths in millimetres.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from BreastBiomechLib.segmentation.morphology import ball, largest_component, local_mean
from BreastBiomechLib.segmentation.volume import VoxelGrid


def otsu_threshold(values: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold of ``values`` (the level that maximises the between-class variance)."""
    hist, edges = np.histogram(values, bins=bins)
    centres = 0.5 * (edges[:-1] + edges[1:])
    weight0 = np.cumsum(hist).astype(float)
    weight1 = weight0[-1] - weight0
    sum0 = np.cumsum(hist * centres)
    mean0 = sum0 / np.maximum(weight0, 1)
    mean1 = (sum0[-1] - sum0) / np.maximum(weight1, 1)
    between = weight0 * weight1 * (mean0 - mean1) ** 2
    return float(centres[int(np.argmax(between[:-1]))])


def tissue_beneath(array: np.ndarray, inner: np.ndarray, grid: VoxelGrid, level_mm: float = 6.0,
                   within: np.ndarray | None = None) -> np.ndarray:
    """The local mean intensity (over ``level_mm``) of the tissue 2-5 mm beneath the body surface:
    the outer 3 mm of ``inner`` (the body eroded by 2 mm), within ``within`` if given; 0 where none
    of it is near."""
    shell = inner & ~ndimage.binary_erosion(inner, ball(grid.spacing_zyx, 3.0), border_value=1)
    if within is not None:
        shell &= within
    return local_mean(array.astype(np.float32), shell, level_mm / grid.spacing_zyx)


def body_mask(array: np.ndarray, grid: VoxelGrid, smoothing_mm: float = 1.0,
              surface_fraction: float = 0.3, surface_level_mm: float = 6.0) -> np.ndarray:
    """The body as a boolean array: the largest connected foreground region, holes filled, with
    its surface placed where a voxel is half tissue.

    Foreground is found by Otsu's threshold on the log intensities of the lightly smoothed volume
    (air and tissue differ by an order of magnitude, far more than a bias field changes). Along
    the surface a voxel then belongs to the body when its intensity reaches ``surface_fraction``
    of the local intensity of the tissue 2-5 mm beneath (averaged over ``surface_level_mm``): the
    outermost tissue is skin, about 0.55 of fat in T1-weighted images, so 0.3 is half of the skin
    signal, i.e. the voxel-majority rule of the label maps, and it holds under a bias field.
    Once the breast is known its surface is placed again for whatever tissue is outermost
    (:func:`~BreastBiomechLib.segmentation.breast.breast_surface`)."""
    if not 0 < surface_fraction < 1:
        raise ValueError("surface_fraction must lie between 0 and 1")
    sigma = smoothing_mm / grid.spacing_zyx
    smooth = ndimage.gaussian_filter(array.astype(np.float32), sigma, mode="nearest")
    positive = smooth[smooth > 0]
    if positive.size == 0:
        raise ValueError("the volume has no positive intensities: is it an MR magnitude image?")
    level = np.exp(otsu_threshold(np.log(positive)))
    body = ndimage.binary_fill_holes(largest_component(smooth > level))
    if not body.any():
        raise ValueError("no body found: the volume has no region brighter than the background")

    inner = ndimage.binary_erosion(body, ball(grid.spacing_zyx, 2.0), border_value=1)
    if not inner.any():
        return body
    tissue = tissue_beneath(array, inner, grid, surface_level_mm)
    band = ndimage.binary_dilation(body, ball(grid.spacing_zyx, 2.0)) & ~inner
    keep = inner | (band & (tissue > 0) & (array >= surface_fraction * tissue))
    return ndimage.binary_fill_holes(largest_component(keep))


def air_level(array: np.ndarray, body: np.ndarray, grid: VoxelGrid, clearance_mm: float = 3.0) -> float:
    """The mean intensity of the background more than ``clearance_mm`` from the body: what air
    reads in a magnitude image (Rician noise: sigma * sqrt(pi / 2), about 1.25 noise deviations,
    a quarter of muscle's signal at SNR 15), so that air the body's surface rule took in is told
    from tissue; 0 when the field of view holds no such background."""
    air = ~ndimage.binary_dilation(body, ball(grid.spacing_zyx, clearance_mm))
    return float(array[air].mean()) if air.any() else 0.0
