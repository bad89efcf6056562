"""Images as NRRD or NIfTI files through SimpleITK (geometry in LPS mm, as ITK stores it)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import SimpleITK as sitk

from BreastBiomechLib.errors import InputError, reading
from BreastBiomechLib.io.atomic import atomic_path
from BreastBiomechLib.labels import present_labels

_SUFFIXES = (".nrrd", ".nhdr", ".nii", ".nii.gz", ".mha", ".mhd")


def _check_suffix(path: Path) -> None:
    if not any(path.name.endswith(s) for s in _SUFFIXES):
        raise ValueError(f"{path}: unsupported image file type; use one of {', '.join(_SUFFIXES)}")


def write_image(path: str | Path, image: sitk.Image, compress: bool = True) -> Path:
    """Write ``image`` (geometry and pixel type kept); returns the path."""
    path = Path(path)
    _check_suffix(path)
    with atomic_path(path) as temporary:
        sitk.WriteImage(image, str(temporary), useCompression=compress)
    return path


MAX_SPACING_MM = 50.0  # no MR or label map of a breast has coarser voxels; larger is a unit mistake


def read_image(path: str | Path) -> sitk.Image:
    """Read a 3D image (geometry in LPS mm). A missing file is a ``FileNotFoundError``; one that
    SimpleITK cannot read, that is not 3D, whose geometry is not finite (spacing between 0 and
    50 mm, a finite origin, an orthonormal direction) or whose voxels are not finite numbers
    raises :class:`~BreastBiomechLib.errors.InputError` naming the file and what is wrong."""
    path = Path(path)
    _check_suffix(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such image file")
    try:
        image = sitk.ReadImage(str(path))
    except RuntimeError as exc:
        raise InputError(f"{path}: SimpleITK could not read it ({str(exc).strip().splitlines()[-1]})") from None
    if image.GetDimension() != 3:
        raise InputError(f"{path}: a 3D volume is needed, this image has {image.GetDimension()} dimensions")
    check_geometry(image, str(path))
    if image.GetPixelID() in _FLOAT_PIXELS:
        bad = int(np.count_nonzero(~np.isfinite(sitk.GetArrayViewFromImage(image))))
        if bad:
            raise InputError(f"{path}: {bad} voxel value(s) are not finite numbers (NaN or infinite); replace them "
                             "(e.g. by 0) before using the image")
    return image


_FLOAT_PIXELS = {sitk.sitkFloat32, sitk.sitkFloat64, sitk.sitkVectorFloat32, sitk.sitkVectorFloat64}


def check_geometry(image: sitk.Image, where: str) -> None:
    """Refuse an image whose geometry cannot place it in LPS mm (:class:`InputError`)."""
    spacing = np.asarray(image.GetSpacing(), dtype=np.float64)
    if not (np.isfinite(spacing).all() and (spacing > 0).all() and (spacing <= MAX_SPACING_MM).all()):
        raise InputError(f"{where}: voxel spacing {tuple(spacing.tolist())} mm; each must be above 0 and at most "
                         f"{MAX_SPACING_MM:g} mm (is the spacing in mm?)")
    if not np.isfinite(image.GetOrigin()).all():
        raise InputError(f"{where}: the origin {image.GetOrigin()} is not finite")
    direction = np.asarray(image.GetDirection(), dtype=np.float64).reshape(3, 3)
    if not np.isfinite(direction).all() or not np.allclose(direction @ direction.T, np.eye(3), atol=1e-4):
        raise InputError(f"{where}: the direction matrix is not a rotation (orthonormal); fix the image header")


def read_label_map(path: str | Path) -> sitk.Image:
    """Read a tissue label map: a 3D image of whole values of the label table
    (:mod:`BreastBiomechLib.labels`), at least one labelled voxel. Anything else raises
    :class:`~BreastBiomechLib.errors.InputError` naming the file and what is wrong."""
    from BreastBiomechLib.surface.extract import label_array

    image = read_image(path)
    with reading(path, "label map", "save the segmentation as a label map of the label table's values "
                 "(breastbiomech segment writes one)"):
        present_labels(label_array(image))
    return image
