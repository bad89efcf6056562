"""Pictures put side by side (the Breast Discrepancy report's slice-view screenshot)."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from BreastBiomechLib.visualisation import side_by_side


def _png(path, array, vector=True):
    sitk.WriteImage(sitk.GetImageFromArray(array.astype(np.uint8), isVector=vector), str(path))
    return path


def test_pictures_of_any_height_and_channels_lie_in_one_row(tmp_path):
    red = _png(tmp_path / "red.png", np.tile([200, 0, 0], (4, 3, 1)))
    rgba = _png(tmp_path / "yellow.png", np.tile([200, 200, 0, 255], (6, 2, 1)))
    grey = _png(tmp_path / "grey.png", np.full((2, 5), 90), vector=False)
    row = sitk.GetArrayFromImage(sitk.ReadImage(str(side_by_side([red, rgba, grey], tmp_path / "row.png"))))
    assert row.shape == (6, 10, 3)
    np.testing.assert_array_equal(row[:4, :3], np.tile([200, 0, 0], (4, 3, 1)))
    assert np.all(row[4:, :3] == 0)  # a shorter picture is top-aligned on black
    np.testing.assert_array_equal(row[:, 3:5], np.tile([200, 200, 0], (6, 2, 1)))
    np.testing.assert_array_equal(row[:2, 5:], np.full((2, 5, 3), 90))
    with pytest.raises(ValueError, match="no picture"):
        side_by_side([], tmp_path / "none.png")
