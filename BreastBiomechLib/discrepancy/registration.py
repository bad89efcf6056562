"""The dense residual displacement field: a deformable registration of the FE-predicted
compressed image to the measured one, masked to the breast, with its own accuracy.

Frames and units: LPS millimetres on the measured image's grid. The registration (ITK's fast
symmetric-forces demons, two resolutions) finds ``d(x)`` with measured(x) ~ predicted(x + d(x));
the tissue the measurement shows at ``x`` is where the model puts it at ``x + d(x)``, so the
**residual** ``r(x) = -d(x)`` is measured position minus model position, the same sign as the
landmark residuals (measured minus predicted).

Before registering, each image is divided by its local mean inside the body (a Gaussian of
``normalise_mm``), which removes the two scans' different bias fields and leaves the tissue
contrast; the measured image is cut to the predicted body grown by ``margin_mm`` (the thorax
beyond the fitting mesh is not the model's).

Its **accuracy** is stated two ways on every field: the RMS error with which it recovers a known
smooth displacement applied to the predicted image itself (``known_rms_error_mm`` for a field of
``known_rms_mm``), and, where landmarks exist, the RMS difference between the field at the
measured landmarks and the landmarks' own residual vectors. The field enters the report and the
regions' summaries, not the score tests: its errors are spatially correlated and depend on the
image's texture, so it has no independent-noise likelihood as the landmark and surface features do.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from BreastBiomechLib.timing import staged


@dataclass
class RegistrationSettings:
    """``iterations`` of demons per resolution, ``shrink`` factors of the in-plane axes per level
    (coarse to fine), ``smoothing_mm`` the Gaussian regularising the field (sd, mm, each axis in
    its own voxels), ``normalise_mm`` the local-mean intensity normalisation, ``margin_mm`` how far
    beyond the predicted body the measured image is kept, ``known_mm`` the amplitude of the known
    displacement used to measure the accuracy (0: not measured)."""

    iterations: int = 50
    shrink: tuple[int, ...] = (2, 1)
    smoothing_mm: float = 3.0
    normalise_mm: float = 15.0
    margin_mm: float = 5.0
    known_mm: float = 1.5

    def __post_init__(self) -> None:
        if self.iterations < 1 or not self.shrink or min(self.shrink) < 1:
            raise ValueError("the registration needs iterations >= 1 and shrink factors >= 1")
        if not (self.smoothing_mm > 0 and self.normalise_mm > 0 and self.margin_mm >= 0 and self.known_mm >= 0):
            raise ValueError("smoothing_mm and normalise_mm must be > 0, margin_mm and known_mm >= 0")


@dataclass
class ResidualField:
    """``residual`` (z, y, x, 3) mm LPS on the measured grid (0 outside ``mask``), the ``mask``
    (z, y, x) bool where it is meaningful (inside both bodies, or between them), the grid
    (``like``, the measured image), the ``accuracy`` figures (mm) and the (measured, predicted)
    ``landmarks`` it was checked against (None when there were none)."""

    residual: np.ndarray
    mask: np.ndarray
    like: sitk.Image
    accuracy: dict
    landmarks: tuple | None = None

    @property
    def magnitude(self) -> np.ndarray:
        """|r| (z, y, x) mm, 0 outside the mask."""
        return np.linalg.norm(self.residual, axis=-1)

    def at(self, points_mm: np.ndarray) -> np.ndarray:
        """The residual (K, 3) mm at points (K, 3) LPS of the measured frame (linear interpolation;
        NaN outside the mask or the image)."""
        points = np.atleast_2d(np.asarray(points_mm, float))
        to_index = np.linalg.inv(np.asarray(self.like.GetDirection(), float).reshape(3, 3)
                                 @ np.diag(self.like.GetSpacing()))
        ijk = (points - np.asarray(self.like.GetOrigin(), float)) @ to_index.T
        zyx = ijk[:, ::-1].T
        values = np.stack([ndimage.map_coordinates(self.residual[..., a], zyx, order=1, mode="nearest")
                           for a in range(3)], axis=1)
        size = np.asarray(self.mask.shape)[::-1]
        inside = np.all((ijk >= -0.5) & (ijk <= size - 0.5), axis=1)
        inside[inside] = ndimage.map_coordinates(self.mask.astype(np.float32), zyx[:, inside], order=0) > 0
        values[~inside] = np.nan
        return values

    def image(self) -> sitk.Image:
        """The field as a vector image (float64, LPS mm) on the measured grid, for Slicer or ITK."""
        image = sitk.GetImageFromArray(self.residual.astype(np.float64), isVector=True)
        image.CopyInformation(self.like)
        return image

    def magnitude_image(self) -> sitk.Image:
        image = sitk.GetImageFromArray(self.magnitude.astype(np.float32))
        image.CopyInformation(self.like)
        return image

    @classmethod
    def read(cls, path, accuracy: dict | None = None) -> "ResidualField":
        """A field written by :meth:`image` (a round's residual .nrrd): its mask where the
        residual is not zero (outside its mask it was written as 0), its ``accuracy`` as the
        round's record states it; no landmarks (the record holds their figures)."""
        image = sitk.ReadImage(str(path))
        residual = sitk.GetArrayFromImage(image).astype(float)
        like = sitk.Image(image.GetSize(), sitk.sitkFloat32)
        like.CopyInformation(image)
        return cls(residual, np.any(residual != 0.0, axis=-1), like, dict(accuracy or {}))


def _spacing_zyx(image: sitk.Image) -> np.ndarray:
    return np.asarray(image.GetSpacing(), float)[::-1]


def _normalised(values: np.ndarray, mask: np.ndarray, spacing_zyx: np.ndarray, scale_mm: float) -> np.ndarray:
    """``values`` divided by their local mean over ``mask`` (Gaussian of ``scale_mm``); 0 outside."""
    sd = scale_mm / spacing_zyx
    weight = ndimage.gaussian_filter(mask.astype(np.float32), sd)
    local = ndimage.gaussian_filter(np.where(mask, values, 0).astype(np.float32), sd) / np.maximum(weight, 1e-3)
    typical = float(np.median(values[mask])) if mask.any() else 1.0
    return np.where(mask, values / np.maximum(local, 1e-3 * max(typical, 1e-12)), 0).astype(np.float32)


def _demons(fixed: sitk.Image, moving: sitk.Image, settings: RegistrationSettings) -> np.ndarray:
    """The demons displacement d (z, y, x, 3) mm with fixed(x) ~ moving(x + d(x))."""
    demons = sitk.FastSymmetricForcesDemonsRegistrationFilter()
    demons.SetNumberOfIterations(settings.iterations)
    demons.SetSmoothDisplacementField(True)
    field = None
    for shrink in settings.shrink:
        factors = [shrink, shrink, 1]
        fixed_level = sitk.Shrink(fixed, factors) if shrink > 1 else fixed
        moving_level = sitk.Shrink(moving, factors) if shrink > 1 else moving
        # ITK smooths the field in voxels of the level: the sd per axis that makes it smoothing_mm
        demons.SetStandardDeviations([max(settings.smoothing_mm / s, 0.5) for s in fixed_level.GetSpacing()])
        if field is None:
            field = demons.Execute(fixed_level, moving_level)
        else:
            field = sitk.Resample(field, fixed_level, sitk.Transform(), sitk.sitkLinear, 0.0, sitk.sitkVectorFloat64)
            field = demons.Execute(fixed_level, moving_level, field)
    return sitk.GetArrayFromImage(field)


def _known_displacement(shape: tuple, spacing_zyx: np.ndarray, amplitude_mm: float) -> np.ndarray:
    """A smooth test displacement (z, y, x, 3) mm: one sine period of ~40 mm per axis, each
    component of peak ``amplitude_mm``, in phase quadrature so that no region is still."""
    axes = [np.arange(n) * h for n, h in zip(shape, spacing_zyx)]
    z, y, x = np.meshgrid(*axes, indexing="ij")
    wave = 2 * np.pi / 40.0
    return amplitude_mm * np.stack([np.sin(wave * y + 0.3) * np.cos(wave * z),
                                    np.sin(wave * x + 1.1) * np.cos(wave * z + 0.7),
                                    np.sin(wave * x + 2.0) * np.cos(wave * y + 0.4)], axis=-1)


def _displaced(values: np.ndarray, displacement_zyx3: np.ndarray, spacing_zyx: np.ndarray,
               direction: np.ndarray) -> np.ndarray:
    """``values`` sampled at x + t(x), t (z, y, x, 3) in LPS mm (linear, 0 outside)."""
    offset_ijk = displacement_zyx3 @ np.linalg.inv(direction).T / spacing_zyx[::-1]
    grid = np.indices(values.shape).astype(np.float64)
    coordinates = grid + np.moveaxis(offset_ijk[..., ::-1], -1, 0)
    return ndimage.map_coordinates(values, coordinates, order=1, mode="constant", cval=0.0).astype(np.float32)


@staged("registration")
def residual_field(predicted: sitk.Image, inside: sitk.Image, measured: sitk.Image, body: np.ndarray | None = None,
                   settings: RegistrationSettings | None = None, landmarks=None) -> ResidualField:
    """The residual field of the FE-``predicted`` image (``inside``: its mask of voxels in the
    deformed mesh) against the ``measured`` image on the same grid, with its accuracy.
    ``body``: the measured body mask (z, y, x) (default: found in ``measured``); ``landmarks``:
    (measured, predicted) :class:`~BreastBiomechLib.landmarks.Landmarks` in the compressed frame,
    for the landmark agreement."""
    settings = settings or RegistrationSettings()
    if predicted.GetSize() != measured.GetSize() or not np.allclose(predicted.GetSpacing(), measured.GetSpacing()):
        raise ValueError("the predicted and measured images must share one grid (the fit's predicted image is made on "
                         "the measured image's grid)")
    spacing = _spacing_zyx(measured)
    direction = np.asarray(measured.GetDirection(), float).reshape(3, 3)
    model_body = sitk.GetArrayFromImage(inside) > 0
    if model_body.sum() < 27:
        raise ValueError("the predicted image has (almost) no voxel inside the deformed mesh: nothing to register; "
                         "check that the fit's displacement belongs to this case")
    measured_values = sitk.GetArrayFromImage(measured).astype(np.float32)
    if body is None:
        from BreastBiomechLib.segmentation.body import body_mask
        from BreastBiomechLib.segmentation.volume import check_volume

        body = body_mask(measured_values, check_volume(measured))
    near_model = ndimage.distance_transform_edt(~model_body, sampling=spacing) <= settings.margin_mm
    kept = body & near_model
    fixed_values = _normalised(measured_values, kept, spacing, settings.normalise_mm)
    moving_values = _normalised(sitk.GetArrayFromImage(predicted).astype(np.float32), model_body, spacing,
                                settings.normalise_mm)

    def as_image(values):
        image = sitk.GetImageFromArray(values)
        image.CopyInformation(measured)
        return image

    try:
        d = _demons(as_image(fixed_values), as_image(moving_values), settings)
    except RuntimeError as error:
        raise RuntimeError(f"the deformable registration of the predicted to the measured image failed: {error}") from None
    mask = ndimage.binary_dilation(kept | model_body)  # one voxel more: the skin's own landmarks
    residual = np.where(mask[..., None], -d, 0.0)
    accuracy = {}
    if settings.known_mm > 0:
        known = _known_displacement(fixed_values.shape, spacing, settings.known_mm)
        shifted = _displaced(moving_values, known, spacing, direction)
        recovered = _demons(as_image(shifted), as_image(moving_values), settings)
        inner = ndimage.binary_erosion(model_body, iterations=2)
        error = np.linalg.norm(recovered - known, axis=-1)[inner]
        accuracy["known_rms_mm"] = float(np.sqrt(np.mean(np.sum(known[inner] ** 2, axis=-1))))
        accuracy["known_rms_error_mm"] = float(np.sqrt(np.mean(error ** 2)))
    field = ResidualField(residual, mask, measured, accuracy, landmarks)
    if landmarks is not None:
        measured_landmarks, predicted_landmarks = landmarks
        marked = measured_landmarks.positions - predicted_landmarks.positions
        sampled = field.at(measured_landmarks.positions)
        ok = np.all(np.isfinite(sampled), axis=1)
        if ok.any():
            accuracy["landmarks"] = int(ok.sum())
            accuracy["landmark_rms_difference_mm"] = float(np.sqrt(np.mean(np.sum((sampled[ok] - marked[ok]) ** 2, 1))))
            accuracy["landmark_rms_residual_mm"] = float(np.sqrt(np.mean(np.sum(marked[ok] ** 2, 1))))
    return field


def residual_field_of(fitted, displacement_mm: np.ndarray, body: np.ndarray | None = None,
                      settings: RegistrationSettings | None = None) -> ResidualField:
    """The residual field of the model of ``fitted`` (a
    :class:`~BreastBiomechLib.discrepancy.fitted.FittedCase`) whose solution is the nodal
    ``displacement_mm`` (N, 3), against the case's measured image."""
    predicted = fitted.problem.warper.predict(displacement_mm)
    landmarks = None
    if fitted.reference is not None:
        from BreastBiomechLib.landmarks import map_landmarks

        landmarks = (fitted.measured, map_landmarks(fitted.mesh, displacement_mm, fitted.reference))
    return residual_field(predicted.image, predicted.inside, fitted.measured_image, body, settings, landmarks)


def field_by_region(field: ResidualField, nodes_mm: np.ndarray, displacement_mm: np.ndarray,
                    regions: np.ndarray) -> dict:
    """The residual field's magnitude at the fitting mesh's nodes, moved by ``displacement_mm``
    (the model's compressed positions), summarised per node region (``regions``, one name per
    node): node count, mean and RMS |r| (mm). Nodes where the field is not defined are left out."""
    values = field.at(np.asarray(nodes_mm, float) + np.asarray(displacement_mm, float))
    magnitude = np.linalg.norm(values, axis=1)
    out = {}
    for name in sorted(set(np.asarray(regions).tolist())):
        chosen = (np.asarray(regions) == name) & np.isfinite(magnitude)
        if chosen.any():
            out[name] = {"nodes": int(chosen.sum()), "mean_mm": float(magnitude[chosen].mean()),
                         "rms_mm": float(np.sqrt(np.mean(magnitude[chosen] ** 2)))}
    return out
