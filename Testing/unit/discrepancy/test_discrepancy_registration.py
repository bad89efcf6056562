"""The residual displacement field (discrepancy/registration.py): it recovers a known
displacement between a textured "predicted" image and a "measured" one with another bias field,
with the sign of the landmark residuals (measured minus model), and states its own accuracy."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from scipy import ndimage

from BreastBiomechLib.discrepancy.registration import (RegistrationSettings, ResidualField, field_by_region,
                                                       residual_field)
from BreastBiomechLib.landmarks import Landmarks

SPACING = (1.5, 1.5, 3.0)
ORIGIN = (-40.0, -30.0, -20.0)


def image_of(values: np.ndarray) -> sitk.Image:
    image = sitk.GetImageFromArray(values.astype(np.float32))
    image.SetSpacing(SPACING)
    image.SetOrigin(ORIGIN)
    return image


def lps_grid(shape) -> np.ndarray:
    """The LPS position (z, y, x, 3) mm of each voxel centre."""
    k, j, i = np.indices(shape)
    return np.asarray(ORIGIN) + np.stack([i, j, k], axis=-1) * np.asarray(SPACING)


@pytest.fixture(scope="module")
def pair():
    """A textured ellipsoidal body (the model's prediction) and the same tissue moved by a known
    smooth displacement, under another bias field (the measurement)."""
    shape = (24, 48, 56)
    rng = np.random.default_rng(4)
    texture = 1.0 + 0.6 * np.tanh(4 * ndimage.gaussian_filter(rng.standard_normal(shape), (0.8, 1.6, 1.6)))
    x = lps_grid(shape)
    body = np.sum(((x - [2.0, 5.0, 14.0]) / [33.0, 26.0, 26.0]) ** 2, axis=-1) <= 1.0
    predicted = np.where(body, texture, 0.02)
    # the true residual r(x) (measured minus model position): the tissue shown at x in the
    # measurement is where the model puts it at x - r(x)
    r = 1.5 * np.stack([np.exp(-np.sum(((x - [10.0, 5.0, 12.0]) / 14.0) ** 2, axis=-1)),
                        -np.exp(-np.sum(((x - [-8.0, 0.0, 16.0]) / 14.0) ** 2, axis=-1)),
                        np.zeros(shape)], axis=-1)
    back = (x - r - np.asarray(ORIGIN)) / np.asarray(SPACING)
    measured = ndimage.map_coordinates(predicted, back[..., ::-1].transpose(3, 0, 1, 2), order=1, cval=0.02)
    bias = 1.0 + 0.2 * (x[..., 0] - x[..., 0].mean()) / np.ptp(x[..., 0])
    inside = image_of(body.astype(np.uint8))
    return image_of(predicted), sitk.Cast(inside, sitk.sitkUInt8), image_of(measured * bias), body, r


def test_recovers_a_known_residual_with_the_landmark_sign(pair):
    predicted, inside, measured, body, r = pair
    points = np.array([[10.0, 5.0, 12.0], [-8.0, 0.0, 16.0], [0.0, 5.0, 14.0]])
    marked = Landmarks(points, ["a", "b", "c"])
    sampled_true = ResidualField(r, body, measured, {}).at(points)
    model = Landmarks(points - sampled_true, ["a", "b", "c"])
    field = residual_field(predicted, inside, measured, body=body, landmarks=(marked, model))
    inner = ndimage.binary_erosion(body, iterations=3)
    error = np.linalg.norm(field.residual - r, axis=-1)[inner]
    size = np.linalg.norm(r, axis=-1)[inner]
    assert np.sqrt(np.mean(error ** 2)) < 0.5 * np.sqrt(np.mean(size ** 2))
    # the sign: the field points as the true residual does where it is large
    for p, truth in zip(points[:2], sampled_true[:2]):
        assert field.at(p[None])[0] @ truth > 0.5 * truth @ truth
    accuracy = field.accuracy
    assert accuracy["known_rms_mm"] > 0.5 and accuracy["known_rms_error_mm"] < 0.5 * accuracy["known_rms_mm"]
    assert accuracy["landmarks"] == 3
    assert accuracy["landmark_rms_difference_mm"] < 0.6 * accuracy["landmark_rms_residual_mm"]
    # a vector image on the measured grid, 0 outside the mask; NaN outside the image
    image = field.image()
    assert image.GetNumberOfComponentsPerPixel() == 3 and image.GetSize() == measured.GetSize()
    assert np.all(field.residual[~field.mask] == 0)
    assert np.all(np.isnan(field.at(np.array([[500.0, 0.0, 0.0]]))))


def test_no_residual_where_the_model_is_right(pair):
    predicted, inside, _, body, _ = pair
    field = residual_field(predicted, inside, predicted, body=body, settings=RegistrationSettings(known_mm=0))
    assert np.percentile(field.magnitude[body], 95) < 0.15
    assert "known_rms_error_mm" not in field.accuracy


def test_summary_by_region(pair):
    predicted, inside, measured, body, r = pair
    field = ResidualField(r, body, measured, {})
    nodes = np.array([[10.0, 5.0, 12.0], [-8.0, 0.0, 16.0], [0.0, 5.0, 30.0], [400.0, 0.0, 0.0]])
    summary = field_by_region(field, nodes, np.zeros_like(nodes), np.array(["left", "right", "right", "left"]))
    assert summary["left"]["nodes"] == 1  # the node outside the image is left out
    assert summary["left"]["mean_mm"] == pytest.approx(1.5, abs=0.1)
    assert summary["right"]["nodes"] == 2


def test_bad_input_is_refused(pair):
    predicted, inside, measured, body, _ = pair
    with pytest.raises(ValueError, match="one grid"):
        residual_field(sitk.Shrink(predicted, [2, 2, 1]), inside, measured, body=body)
    with pytest.raises(ValueError, match="nothing to register"):
        residual_field(predicted, inside * 0, measured, body=body)
    with pytest.raises(ValueError, match="iterations"):
        RegistrationSettings(iterations=0)
