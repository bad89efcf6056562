"""Compressed "measured" phantom cases: a truth simulation imaged like a second scan."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from BreastBiomechLib.landmarks import map_landmarks
from BreastBiomechLib.phantom import PhantomParameters, generate_phantom
from BreastBiomechLib.phantom.compressed import TruthModel, compress_phantom, table1_truth
from BreastBiomechLib.similarity import Similarity
from BreastBiomechLib.warping import ImageWarper


@pytest.fixture(scope="module")
def cases():
    """A small coarse phantom (heterogeneous default truth materials), compressed by 25 % LR
    on a 6 mm truth mesh, on the CPU."""
    case = generate_phantom(PhantomParameters(seed=2, volume_cm3=450.0, spacing_mm=(1.5, 1.5, 3.0)))
    return case, compress_phantom(case, TruthModel(compression=0.25, edge_mm=6.0), device="cpu")


def test_the_truth_solve_closes_the_plates_by_the_compression(cases):
    _, compressed = cases
    assert compressed.summary["solve_status"] == "completed"
    mesh = compressed.mesh
    skin = mesh.nodes[mesh.node_set("breast_skin")]
    assert compressed.summary["plate_gap_mm"] == pytest.approx(0.75 * np.ptp(skin[:, 0]), rel=1e-6)
    # the nipple, in contact with neither plate, stays on the breast's midline between them
    nipple = np.argmin(mesh.nodes[:, 1])
    x = (mesh.nodes + mesh.point_data["displacement"])[nipple, 0]
    low, high = sorted(plate["point"][0] for plate in compressed.plates)
    assert low < x < high
    assert all(force > 0.5 for force in compressed.summary["plate_forces_N"].values())


def test_the_measured_image_is_the_warped_signal_with_its_own_noise(cases):
    case, compressed = cases
    mesh = compressed.mesh
    clean = ImageWarper(mesh, case.signal, compressed.image, device="cpu").predict(mesh.point_data["displacement"])
    inside = sitk.GetArrayFromImage(clean.inside).astype(bool)
    measure = Similarity(compressed.image, inside, device="cpu")
    assert measure.ncc(clean.image) > 0.9           # the same anatomy under +-20 % bias and noise
    assert measure.nmi(clean.image) > 1.2
    background = sitk.GetArrayFromImage(compressed.image)[~inside]
    sigma = 1000.0 / case.parameters.snr
    assert np.median(background) == pytest.approx(sigma * np.sqrt(2 * np.log(2)), rel=0.05)  # Rayleigh median


def test_landmarks_follow_the_truth_displacement(cases):
    case, compressed = cases
    moved = map_landmarks(compressed.mesh, compressed.mesh.point_data["displacement"], case.landmarks)
    np.testing.assert_allclose(compressed.landmarks.positions, moved.positions)
    assert compressed.landmarks.labels == case.landmarks.labels
    shift = np.abs(compressed.landmarks.positions - case.landmarks.positions)
    assert shift[:, 0].max() > 5.0  # squeezed left-right


def test_presets_and_checks():
    assert table1_truth(4).compression == pytest.approx(0.504)
    assert table1_truth(3).materials["fat"]["eta"] > 0 and "eta" not in table1_truth(1).materials["fat"]
    with pytest.raises(ValueError, match="compression must lie"):
        TruthModel(compression=0.9)
    with pytest.raises(ValueError, match="cases 1-5"):
        table1_truth(6)
