"""Pictures of a diagnosis round: the residual field's magnitude over the measured compressed
image, before and after the refit, on three orthogonal slices, with the landmark residuals.

Slices in millimetres, LPS, radiological convention as :mod:`BreastBiomechLib.visualisation`
draws them; one colour scale (mm) shared by all rows so that before and after compare.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from BreastBiomechLib.discrepancy.registration import ResidualField
from BreastBiomechLib.timing import staged
from BreastBiomechLib.visualisation import image_bounds, orthogonal_views

SHOWN_FROM_MM = 0.25  # residual below this is drawn transparent


def hot_spot(field: ResidualField, smoothing_mm: float = 5.0) -> np.ndarray:
    """The LPS point (mm) where the smoothed residual magnitude is largest (the slices' centre)."""
    sd = smoothing_mm / np.asarray(field.like.GetSpacing(), float)[::-1]
    smooth = ndimage.gaussian_filter(field.magnitude, sd)
    k, j, i = np.unravel_index(int(np.argmax(smooth)), smooth.shape)
    return np.asarray(field.like.TransformIndexToPhysicalPoint((int(i), int(j), int(k))), float)


@staged("pictures")
def save_residual_maps(path: str | Path, measured: sitk.Image, rows: list[tuple[str, ResidualField, tuple | None]],
                       centre_mm=None, title: str = "", limit_mm: float | None = None) -> Path:
    """Save a PNG with one row per ``(name, field, landmarks)`` in ``rows``: axial, sagittal and
    coronal slices of ``measured`` through ``centre_mm`` (LPS; default the first field's
    :func:`hot_spot`) with the residual magnitude in colour (mm, shared scale up to ``limit_mm``,
    default the first field's 99th percentile) and, where ``landmarks`` is (measured, predicted)
    Landmarks, an arrow from each predicted to its measured landmark (x5 so that millimetres show)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not rows:
        raise ValueError("no residual field to draw")
    image = sitk.DICOMOrient(measured, "LPS")
    volume = sitk.GetArrayFromImage(image).astype(np.float32)
    lo, hi = image_bounds(image)
    centre = np.asarray(centre_mm if centre_mm is not None else hot_spot(rows[0][1]), float)
    views, _ = orthogonal_views(image, centre)
    grey = float(np.percentile(volume, 99.5)) or 1.0
    first = rows[0][1]
    limit = limit_mm or max(float(np.percentile(first.magnitude[first.mask], 99)) if first.mask.any() else 1.0, 0.5)
    widths = [hi[a] - lo[a] for *_, (a, _b) in views]
    fig, axes = plt.subplots(len(rows), 3, figsize=(15, 4.6 * len(rows) + 0.6), squeeze=False,
                             layout="constrained", gridspec_kw={"width_ratios": widths})
    shown = None
    for row, (name, field, landmarks) in zip(axes, rows):
        magnitude = sitk.GetArrayFromImage(sitk.DICOMOrient(field.magnitude_image(), "LPS"))
        for ax, (view, take, extent, org, normal, (ia, ib)) in zip(row, views):
            ax.imshow(take(volume), cmap="gray", vmin=0, vmax=grey, extent=extent, origin=org, interpolation="nearest")
            plane = take(magnitude)
            shown = ax.imshow(np.ma.masked_less(plane, SHOWN_FROM_MM), cmap="inferno", vmin=0, vmax=limit,
                              alpha=0.75, extent=extent, origin=org, interpolation="nearest")
            if landmarks is not None:
                measured_points, predicted_points = landmarks[0].positions, landmarks[1].positions
                near = np.abs(measured_points[:, normal] - centre[normal]) <= 10.0
                for m, p in zip(measured_points[near], predicted_points[near]):
                    ax.annotate("", xy=(p[ia] + 5 * (m[ia] - p[ia]), p[ib] + 5 * (m[ib] - p[ib])), xytext=(p[ia], p[ib]),
                                arrowprops={"arrowstyle": "->", "color": "cyan", "lw": 1.0})
            ax.set_xlim(extent[0], extent[1])
            ax.set_ylim(extent[2], extent[3])
            ax.set_title(f"{name}: {view} ({'LPS'[normal]} = {centre[normal]:.0f} mm)", fontsize=9)
            ax.set_xlabel(f"{'LPS'[ia]} (mm)")
            ax.set_ylabel(f"{'LPS'[ib]} (mm)")
    fig.colorbar(shown, ax=axes.ravel().tolist(), shrink=0.8, label="residual displacement |r| (mm)")
    if title:
        fig.suptitle(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
