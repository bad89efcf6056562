"""Pictures for reports and the README: orthogonal slices with label contours and landmarks.

Slices are drawn in millimetres in LPS, radiological convention (patient left on the right),
anterior at the top of the axial view and superior at the top of the sagittal and coronal views.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import SimpleITK as sitk

from BreastBiomechLib import labels as lt
from BreastBiomechLib.landmarks import Landmarks
from BreastBiomechLib.timing import staged


def _axis_aligned(image: sitk.Image) -> sitk.Image:
    """The same image with its axes permuted/flipped to L, P, S (identity direction)."""
    return sitk.DICOMOrient(image, "LPS")


def image_bounds(image: sitk.Image) -> tuple[np.ndarray, np.ndarray]:
    """The LPS corners (mm) of an axis-aligned image's voxel boxes: (lowest, highest)."""
    origin, spacing, size = np.array(image.GetOrigin()), np.array(image.GetSpacing()), np.array(image.GetSize())
    return origin - spacing / 2, origin + spacing * (size - 0.5)


def orthogonal_views(image: sitk.Image, centre_mm) -> tuple[list, np.ndarray]:
    """The axial, sagittal and coronal views of an axis-aligned image (:func:`_axis_aligned`)
    through the voxel nearest ``centre_mm`` (LPS): per view (name, slice of a (z, y, x) array,
    imshow extent in mm, imshow origin, the axis normal to the slice, the in-plane axes), and
    the voxel index (i, j, k)."""
    origin, spacing, size = np.array(image.GetOrigin()), np.array(image.GetSpacing()), np.array(image.GetSize())
    lo, hi = image_bounds(image)
    idx = np.clip(np.rint((np.asarray(centre_mm, float) - origin) / spacing).astype(int), 0, size - 1)
    views = [
        ("axial", lambda v: v[idx[2]], (lo[0], hi[0], hi[1], lo[1]), "upper", 2, (0, 1)),
        ("sagittal", lambda v: v[:, :, idx[0]], (lo[1], hi[1], lo[2], hi[2]), "lower", 0, (1, 2)),
        ("coronal", lambda v: v[:, idx[1], :], (lo[0], hi[0], lo[2], hi[2]), "lower", 1, (0, 2)),
    ]
    return views, idx


@staged("pictures")
def save_overview(path: str | Path, image: sitk.Image, label_image: sitk.Image | None = None,
                  landmarks: Landmarks | None = None, centre_mm=None, title: str = "",
                  landmark_slab_mm: float = 6.0) -> Path:
    """Save a PNG with axial, sagittal and coronal slices through ``centre_mm`` (LPS; default:
    the nipple landmark if present, else the image centre)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    image = _axis_aligned(image)
    volume = sitk.GetArrayFromImage(image).astype(np.float32)  # z, y, x
    label_volume = sitk.GetArrayFromImage(_axis_aligned(label_image)) if label_image is not None else None
    origin, spacing = np.array(image.GetOrigin()), np.array(image.GetSpacing())
    lo, hi = image_bounds(image)
    if centre_mm is None:
        if landmarks is not None and "nipple" in landmarks.labels:
            centre_mm = landmarks.position("nipple") + np.array([0.0, 0.35 * (hi[1] - lo[1]), 0.0])
        else:
            centre_mm = (lo + hi) / 2
    views, idx = orthogonal_views(image, centre_mm)
    vmax = float(np.percentile(volume, 99.5)) or 1.0

    widths = [hi[a] - lo[a] for *_, (a, _b) in views]
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.4), gridspec_kw={"width_ratios": widths})
    for ax, (name, take, extent, org, normal, (ia, ib)) in zip(axes, views):
        ax.imshow(take(volume), cmap="gray", vmin=0, vmax=vmax, extent=extent, origin=org,
                  interpolation="nearest")
        if label_volume is not None:
            plane = take(label_volume)
            for tissue in lt.TISSUES:
                mask = (plane == tissue.label).astype(float)
                if mask.any():
                    ax.contour(mask, levels=[0.5], colors=[tissue.color], linewidths=0.9,
                               extent=extent, origin=org)
        if landmarks is not None and len(landmarks):
            near = np.abs(landmarks.positions[:, normal] - (origin[normal] + idx[normal] * spacing[normal]))
            sel = near <= landmark_slab_mm
            p = landmarks.positions
            ax.scatter(p[~sel, ia], p[~sel, ib], s=10, c="none", edgecolors="yellow", linewidths=0.6)
            ax.scatter(p[sel, ia], p[sel, ib], s=22, c="yellow", edgecolors="black", linewidths=0.5)
            for k in np.flatnonzero(sel):
                ax.annotate(landmarks.labels[k], (p[k, ia], p[k, ib]), color="yellow", fontsize=6,
                            xytext=(3, 3), textcoords="offset points")
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.set_title(f"{name} ({'LPS'[normal]} = {origin[normal] + idx[normal] * spacing[normal]:.0f} mm)")
        ax.set_xlabel(f"{'LPS'[ia]} (mm)")
        ax.set_ylabel(f"{'LPS'[ib]} (mm)")
    handles = [plt.Line2D([], [], color=t.color, label=t.name) for t in lt.TISSUES
               if label_volume is not None and (label_volume == t.label).any()]
    if handles:
        fig.legend(handles=handles, loc="lower center", ncol=len(handles), frameon=False)
    if title:
        fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.05, 1, 0.97))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


@staged("pictures")
def side_by_side(pictures, path: str | Path) -> Path:
    """The PNG ``pictures`` (paths; RGB or RGBA, any heights) in one row, top-aligned on black,
    written to ``path``: a screenshot of several views (e.g. the slice views alone, not the
    layout's plots and 3D view)."""
    images = []
    for picture in pictures:
        array = sitk.GetArrayFromImage(sitk.ReadImage(str(picture)))
        if array.ndim == 2:
            array = np.repeat(array[..., None], 3, axis=2)
        images.append(array[..., :3].astype(np.uint8))
    if not images:
        raise ValueError("no picture to put side by side")
    height = max(a.shape[0] for a in images)
    row = np.zeros((height, sum(a.shape[1] for a in images), 3), np.uint8)
    left = 0
    for array in images:
        row[:array.shape[0], left:left + array.shape[1]] = array
        left += array.shape[1]
    sitk.WriteImage(sitk.GetImageFromArray(row, isVector=True), str(path))
    return Path(path)
