"""The synthetic breast phantom: requested volumes and densities, ground truth consistency,
MR signal model (noise and bias), landmarks, files, determinism."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import SimpleITK as sitk

from BreastBiomechLib import labels as lt
from BreastBiomechLib.phantom import (PhantomParameters, generate_phantom, read_phantom, table1_case,
                                      write_phantom)
from BreastBiomechLib.phantom.parameters import INTENSITY


@pytest.fixture(scope="module")
def small_case():
    params = PhantomParameters(seed=7, volume_cm3=450.0, density=0.3, tumour_diameter_mm=12.0, snr=25.0,
                               bias_strength=0.2, skin_separate=True)
    return generate_phantom(params)


def _array(image):
    return sitk.GetArrayFromImage(image)


def test_requested_volume_density_and_tumour_size(small_case):
    s = small_case.summary
    assert s["breast_volume_cm3"] == pytest.approx(450.0, rel=0.03)
    assert s["glandular_density"] == pytest.approx(0.3, abs=0.005)
    assert s["tumour_equivalent_diameter_mm"] == pytest.approx(12.0, rel=0.05)
    # the summary is what the fraction images hold
    voxel_cm3 = np.prod(small_case.image.GetSpacing()) / 1000
    fat = _array(small_case.fractions["fat"]).sum() * voxel_cm3
    assert fat == pytest.approx(s["tissue_volumes_cm3"]["fat"], rel=1e-4)


def test_fractions_and_labels_are_consistent(small_case):
    stack = np.stack([_array(small_case.fractions[t.name]) for t in lt.TISSUES])
    assert stack.min() >= 0 and stack.sum(axis=0).max() <= 1 + 1e-5
    labels = _array(small_case.labels)
    assert set(np.unique(labels)) == {0, 1, 2, 3, 4, 5}
    # every labelled voxel is mostly tissue, and its label is the largest fraction
    tissue = labels > 0
    assert np.all(stack.sum(axis=0)[tissue] >= 0.5 - 1e-6)
    winner = np.array([t.label for t in lt.TISSUES])[np.argmax(stack, axis=0)]
    np.testing.assert_array_equal(winner[tissue], labels[tissue])
    # partial volume: voxels at tissue boundaries hold mixtures
    assert np.count_nonzero((stack > 0.05) & (stack < 0.95)) > 0.05 * np.count_nonzero(tissue)


def test_skin_is_a_thin_outer_layer_and_folds_into_fat_by_default(small_case):
    skin_cm3 = small_case.summary["tissue_volumes_cm3"]["skin"]
    assert 0.03 < skin_cm3 / small_case.summary["breast_volume_cm3"] < 0.15
    folded = generate_phantom(PhantomParameters(seed=7, volume_cm3=450.0, density=0.3, tumour_diameter_mm=12.0,
                                                snr=25.0, bias_strength=0.2))
    assert "skin" not in folded.fractions
    assert lt.SKIN.label not in np.unique(_array(folded.labels))
    assert folded.summary["breast_volume_cm3"] == pytest.approx(small_case.summary["breast_volume_cm3"], rel=1e-6)


def test_noise_and_bias_follow_the_requested_signal_model(small_case):
    image, labels = _array(small_case.image), _array(small_case.labels)
    sigma = INTENSITY["fat"] / 25.0
    # air in front of the nipple is pure Rician noise of a zero signal: Rayleigh, mean sigma*sqrt(pi/2)
    nipple_row = small_case.image.TransformPhysicalPointToIndex(tuple(small_case.landmarks.position("nipple")))[1]
    air = image[:, : nipple_row - 3, :]
    assert air.size > 10000
    assert air.mean() == pytest.approx(sigma * np.sqrt(np.pi / 2), rel=0.05)
    bias = _array(small_case.bias_field)[labels > 0]
    assert bias.min() == pytest.approx(0.8, abs=0.02) and bias.max() == pytest.approx(1.2, abs=0.02)
    # pure fat voxels: mean near 1000 x bias, spread about sigma
    fat = _array(small_case.fractions["fat"]) > 0.999
    ratio = image[fat] / _array(small_case.bias_field)[fat]
    assert np.median(ratio) == pytest.approx(INTENSITY["fat"], rel=0.03)
    # contrast: fat brighter than glandular brighter than muscle, tumour darkest of the breast
    means = {t.name: np.median((image / _array(small_case.bias_field))[_array(small_case.fractions[t.name]) > 0.999])
             for t in (lt.FAT, lt.GLANDULAR, lt.MUSCLE, lt.TUMOUR)}
    assert means["fat"] > means["glandular"] > means["muscle"] > means["tumour"]


def test_seventeen_landmarks_at_their_features(small_case):
    lm = small_case.landmarks
    assert len(lm) == 17
    assert lm.labels == [f"L{i:02d}" for i in range(1, 13)] + ["F1", "F2", "F3", "F4", "nipple"]
    labels = small_case.labels
    fractions = small_case.fractions

    def value(image, p):
        return image[image.TransformPhysicalPointToIndex(tuple(p))]

    assert "tumour centre" in lm.descriptions
    for p, text in zip(lm.positions, lm.descriptions):
        if text == "tumour centre":
            assert value(labels, p) == lt.TUMOUR.label
        elif text in ("duct branching", "lobule centre"):
            assert value(fractions["glandular"], p) > 0.3
        elif text.startswith("pectoral fascia"):
            assert value(fractions["muscle"], p) > 0.1 or value(fractions["muscle"], p + [0, 1.0, 0]) > 0.5
    # skin fiducials and nipple lie on the skin: tissue just inside, air just outside
    centre = lm.positions[:12].mean(axis=0)
    for label in ["F1", "F2", "F3", "F4", "nipple"]:
        p = lm.position(label)
        outward = (p - centre) / np.linalg.norm(p - centre)
        assert value(labels, p - 3.0 * outward) in (lt.SKIN.label, lt.FAT.label, lt.GLANDULAR.label)
        assert value(labels, p + 3.0 * outward) == 0
    # spread: internal landmarks are not bunched together
    d = np.linalg.norm(lm.positions[:12, None] - lm.positions[None, :12], axis=-1)
    assert d[np.triu_indices(12, 1)].min() > 5.0


@pytest.mark.slow
def test_deterministic_in_the_seed(small_case):
    a = small_case
    b = generate_phantom(a.parameters)
    c = generate_phantom(replace(a.parameters, seed=a.parameters.seed + 1))
    np.testing.assert_array_equal(_array(a.image), _array(b.image))
    np.testing.assert_array_equal(a.landmarks.positions, b.landmarks.positions)
    assert not np.array_equal(_array(a.labels), _array(c.labels))


@pytest.mark.slow
def test_finer_subvoxels_leave_fewer_truth_voxels_tied_at_half():
    """1.5 mm voxels drawn on 2 sub-voxels per axis (the default, as every earlier case) tie two
    tissues at exactly half in many border voxels; at most 0.7 mm (4 per axis) far fewer, and the
    volumes agree."""
    params = dict(seed=3, volume_cm3=420.0, density=0.25, spacing_mm=(1.5, 1.5, 1.5))

    def ties(case):
        stack = np.sort(np.stack([_array(f) for f in case.fractions.values()]), axis=0)
        return int(np.count_nonzero((stack[-1] == 0.5) & (stack[-2] == 0.5)))

    coarse = generate_phantom(PhantomParameters(**params))
    fine = generate_phantom(PhantomParameters(subvoxel_mm=0.7, **params))
    assert ties(coarse) > 100 and ties(fine) < ties(coarse) / 4
    assert fine.summary["breast_volume_cm3"] == pytest.approx(coarse.summary["breast_volume_cm3"], rel=0.01)


def test_files_round_trip(small_case, tmp_path):
    paths = write_phantom(small_case, tmp_path / "case")
    for key in ("mr", "labels", "landmarks", "parameters", "overview", "fraction_glandular", "bias_field"):
        assert paths[key].is_file(), key
    back = read_phantom(tmp_path / "case")
    np.testing.assert_array_equal(_array(back.labels), _array(small_case.labels))
    np.testing.assert_allclose(_array(back.image), _array(small_case.image))
    np.testing.assert_allclose(back.landmarks.positions, small_case.landmarks.positions)
    assert back.parameters == small_case.parameters
    assert back.image.GetSpacing() == pytest.approx((1.0, 1.0, 2.5))


def test_bad_parameters_are_named():
    with pytest.raises(ValueError, match="volume_cm3"):
        PhantomParameters(volume_cm3=100.0)
    with pytest.raises(ValueError, match="density"):
        PhantomParameters(density=0.9)
    with pytest.raises(ValueError, match="subvoxel_mm"):
        PhantomParameters(subvoxel_mm=0.1)
    with pytest.raises(ValueError, match="unknown phantom parameters"):
        PhantomParameters.from_dict({"volume": 500})
    with pytest.raises(ValueError, match="cases 1-5"):
        table1_case(6)
    with pytest.raises(FileNotFoundError, match="phantom case folder"):
        read_phantom("/nonexistent")


@pytest.mark.slow
@pytest.mark.parametrize("number", [1, 2, 3, 4, 5])
def test_table1_cases_have_the_requested_volume_and_density(number):
    params = table1_case(number)
    case = generate_phantom(params)
    assert case.summary["breast_volume_cm3"] == pytest.approx(params.volume_cm3, rel=0.015)
    assert case.summary["glandular_density"] == pytest.approx(params.density, abs=0.005)
    has_tumour = lt.TUMOUR.label in np.unique(_array(case.labels))
    assert has_tumour == (params.tumour_diameter_mm > 0)
    assert len(case.landmarks) == 17
