"""Images as NRRD or NIfTI files through SimpleITK (geometry in LPS mm, as ITK stores it)."""

from __future__ import annotations

from pathlib import Path

import SimpleITK as sitk

_SUFFIXES = (".nrrd", ".nhdr", ".nii", ".nii.gz", ".mha", ".mhd")


def _check_suffix(path: Path) -> None:
    if not any(path.name.endswith(s) for s in _SUFFIXES):
        raise ValueError(f"{path}: unsupported image file type; use one of {', '.join(_SUFFIXES)}")


def write_image(path: str | Path, image: sitk.Image, compress: bool = True) -> Path:
    """Write ``image`` (geometry and pixel type kept); returns the path."""
    path = Path(path)
    _check_suffix(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sitk.WriteImage(image, str(path), useCompression=compress)
    return path


def read_image(path: str | Path) -> sitk.Image:
    """Read a 3D image; a clear error if it is missing, unreadable or not 3D."""
    path = Path(path)
    _check_suffix(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such image file")
    try:
        image = sitk.ReadImage(str(path))
    except RuntimeError as exc:
        raise ValueError(f"{path}: SimpleITK could not read it ({str(exc).strip().splitlines()[-1]})") from None
    if image.GetDimension() != 3:
        raise ValueError(f"{path}: a 3D volume is needed, this image has {image.GetDimension()} dimensions")
    return image
