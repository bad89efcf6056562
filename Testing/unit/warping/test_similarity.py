"""NMI (the seed's eq. (16)) and NCC on the device, against an independent histogram computation
and the measures' known values."""

from __future__ import annotations

import numpy as np
import pytest

from BreastBiomechLib.similarity import Similarity, ncc, nmi


@pytest.fixture(scope="module")
def pair():
    """Two related images (z, y, x) and a mask: b is a nonlinear, noisy function of a."""
    rng = np.random.default_rng(0)
    a = rng.gamma(2.0, 200.0, (20, 40, 50)).astype(np.float32)
    b = (np.sqrt(a) * 30 + rng.normal(0, 40, a.shape)).astype(np.float32)
    mask = rng.random(a.shape) > 0.2
    return a, b, mask


def _reference_nmi(a, b, mask, bins, range_a, range_b):
    """The same definition with numpy's histogram2d and float64 entropies."""
    a = np.clip(a[mask].astype(np.float64), range_a[0], np.nextafter(range_a[1], -np.inf))
    b = np.clip(b[mask].astype(np.float64), range_b[0], np.nextafter(range_b[1], -np.inf))
    counts, _, _ = np.histogram2d(a, b, bins=bins, range=[range_a, range_b])
    p = counts / counts.sum()

    def h(q):
        q = q[q > 0]
        return -(q * np.log(q)).sum()

    return (h(p.sum(axis=1)) + h(p.sum(axis=0))) / h(p.ravel())


@pytest.mark.parametrize("bins", [16, 64])
def test_nmi_matches_an_independent_histogram(pair, bins):
    a, b, mask = pair
    ranges = (float(a[mask].min()), float(a[mask].max())), (float(b[mask].min()), float(b[mask].max()))
    got = nmi(a, b, mask, bins=bins, device="cpu")
    assert got == pytest.approx(_reference_nmi(a, b, mask, bins, *ranges), abs=1e-5)
    # a given, narrower range clips into the edge bins in both
    narrow = (200.0, 900.0), (300.0, 800.0)
    got = nmi(a, b, mask, bins=bins, range_measured=narrow[0], range_predicted=narrow[1], device="cpu")
    assert got == pytest.approx(_reference_nmi(a, b, mask, bins, *narrow), abs=1e-5)


def test_nmi_is_two_for_an_image_with_itself_and_one_for_independent_images(pair):
    a, _, mask = pair
    assert nmi(a, a, mask, device="cpu") == pytest.approx(2.0, abs=1e-6)
    noise = np.random.default_rng(1).normal(0, 1, a.shape).astype(np.float32)
    assert 1.0 <= nmi(a, noise, mask, device="cpu") < 1.02


def test_ncc_matches_the_correlation_coefficient(pair):
    a, b, mask = pair
    assert ncc(a, b, mask, device="cpu") == pytest.approx(np.corrcoef(a[mask], b[mask])[0, 1], abs=1e-6)
    assert ncc(a, 2 * a + 3, mask, device="cpu") == pytest.approx(1.0, abs=1e-6)
    assert ncc(a, -a, device="cpu") == pytest.approx(-1.0, abs=1e-6)


def test_the_loop_form_takes_device_arrays(pair):
    import warp as wp

    a, b, mask = pair
    measure = Similarity(a, mask, bins=32, range_predicted=(float(b.min()), float(b.max())), device="cpu")
    on_device = wp.array(b.ravel(), dtype=float, device="cpu")
    assert measure.nmi(on_device) == pytest.approx(measure.nmi(b), abs=1e-12)
    assert measure.joint_histogram(b).sum() == mask.sum()
    assert measure.ncc(on_device) == pytest.approx(ncc(a, b, mask, device="cpu"), abs=1e-9)


def test_bad_input_is_refused(pair):
    a, b, mask = pair
    with pytest.raises(ValueError, match="mask has"):
        Similarity(a, mask[:5], device="cpu")
    with pytest.raises(ValueError, match="selects no voxel"):
        Similarity(a, np.zeros_like(mask), device="cpu")
    with pytest.raises(ValueError, match="range .* is empty"):
        Similarity(np.ones_like(a), device="cpu")
    with pytest.raises(ValueError, match="predicted image has"):
        Similarity(a, device="cpu").nmi(b[:3])
