"""Compressed "measured" phantom cases: a truth simulation imaged like a second scan."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from BreastBiomechLib.landmarks import map_landmarks
from BreastBiomechLib.phantom.compressed import TruthModel, table1_truth
from BreastBiomechLib.similarity import Similarity
from BreastBiomechLib.warping import ImageWarper


@pytest.fixture(scope="module")
def cases(compressed_case_dir):
    """The undeformed case, what a fit may use, and the truth mesh of the compressed case made
    by the command (conftest.compressed_case_dir), read back from its files."""
    from BreastBiomechLib.io.meshes import read_vtu
    from BreastBiomechLib.phantom import read_phantom
    from BreastBiomechLib.phantom.compressed_files import read_compressed

    return (read_phantom(compressed_case_dir), read_compressed(compressed_case_dir),
            read_vtu(compressed_case_dir / "compressed" / "truth_mesh.vtu"))


def test_the_truth_solve_closes_the_plates_by_the_compression(cases, compressed_case_dir):
    from BreastBiomechLib.phantom.truth_files import read_truth

    _, measured, mesh = cases
    truth = read_truth(compressed_case_dir)
    summary = truth["summary"]
    assert summary["solve_status"] == "completed"
    skin = mesh.nodes[mesh.node_set("breast_skin")]
    assert summary["plate_gap_mm"] == pytest.approx(0.75 * np.ptp(skin[:, 0]), rel=1e-6)
    # the nipple, in contact with neither plate, stays on the breast's midline between them
    nipple = np.argmin(mesh.nodes[:, 1])
    x = (mesh.nodes + mesh.point_data["displacement"])[nipple, 0]
    low, high = sorted(plate["point"][0] for plate in measured.plates)
    assert low < x < high
    assert all(force > 0.5 for force in summary["plate_forces_N"].values())
    # the plates' flat faces end the plate travel anterior to the chest, rounded back to it
    travel = measured.plates[0]["travel_mm"]
    assert travel == pytest.approx(0.125 * np.ptp(skin[:, 0]), rel=1e-6)
    assert all(plate["edge"]["radius"] == pytest.approx(travel) for plate in measured.plates)
    assert (measured.axis, measured.compression) == ("LR", 0.25)
    assert truth["truth"]["materials"]["muscle"]["E"] == 80e3


def test_the_measured_image_is_the_warped_signal_with_its_own_noise(cases):
    case, measured, mesh = cases
    clean = ImageWarper(mesh, case.signal, measured.image, device="cpu").predict(mesh.point_data["displacement"])
    inside = sitk.GetArrayFromImage(clean.inside).astype(bool)
    measure = Similarity(measured.image, inside, device="cpu")
    assert measure.ncc(clean.image) > 0.9           # the same anatomy under +-20 % bias and noise
    assert measure.nmi(clean.image) > 1.2
    background = sitk.GetArrayFromImage(measured.image)[~inside]
    sigma = 1000.0 / case.parameters.snr
    assert np.median(background) == pytest.approx(sigma * np.sqrt(2 * np.log(2)), rel=0.05)  # Rayleigh median


def test_landmarks_follow_the_truth_displacement(cases):
    case, measured, mesh = cases
    moved = map_landmarks(mesh, mesh.point_data["displacement"], case.landmarks)
    np.testing.assert_allclose(measured.landmarks.positions, moved.positions, atol=1e-4)  # float32 in the .vtu
    assert measured.landmarks.labels == case.landmarks.labels
    shift = np.abs(measured.landmarks.positions - case.landmarks.positions)
    assert shift[:, 0].max() > 5.0  # squeezed left-right


def test_presets_and_checks():
    assert table1_truth(4).compression == pytest.approx(0.504)
    assert table1_truth(3).materials["fat"]["eta"] > 0 and "eta" not in table1_truth(1).materials["fat"]
    with pytest.raises(ValueError, match="compression must lie"):
        TruthModel(compression=0.9)
    with pytest.raises(ValueError, match="cases 1-5"):
        table1_truth(6)


def test_the_command_refuses_bad_requests(tmp_path, capsys):
    from BreastBiomechLib.cli import main
    from BreastBiomechLib.phantom.compressed_files import read_compressed

    assert main(["phantom", "--compression", "0.3", "--out", str(tmp_path / "a")]) == 2
    assert "add --compressed" in capsys.readouterr().err
    assert main(["phantom", "--compressed", "--compression", "0.8", "--out", str(tmp_path / "b")]) == 2
    assert "compression must lie" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()  # refused before anything was made
    with pytest.raises(FileNotFoundError, match="not a compressed case"):
        read_compressed(tmp_path)


def test_hidden_effects_change_the_truth_model_and_are_recorded():
    """Each hidden effect of a TruthModel reaches the truth simulation's model (on the small
    hemi-ellipsoid compression, whose chest wall is held by anchor patches): plate friction and
    tilt, a sliding chest wall (with the sentence saying what holds the model), the gravity
    pre-stress (the model starts from the estimated unloaded state); the solve converges and
    moves the breast differently from the seed's model."""
    from BreastBiomechLib.phantom.compressed import TruthModel, with_hidden_effects
    from BreastBiomechLib.solver import DynamicRelaxation, SolverSettings
    from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression
    from BreastBiomechLib.solver.run_case import run_case

    seed = hemi_ellipsoid_compression(10.0)
    relaxation = DynamicRelaxation(load_iterations=300)
    truth = TruthModel(friction=0.5, gravity=[0, -9.81, 0], chest_wall="sliding",
                       plate_tilt_deg=[[0.5, 0.0], [0.0, -0.5]], skin=[50e3, 2.0])
    assert truth.hidden_effects == ["friction 0.5", "gravity pre-stress [0.0, -9.81, 0.0]", "sliding chest wall",
                                    "plate tilt [[0.5, 0.0], [0.0, -0.5]]", "skin 50000 Pa, 2 mm"]
    model, unloaded = with_hidden_effects(seed, truth)
    assert [p.friction for p in model.loading.plates] == [0.5, 0.5]
    assert all(abs(p.normal @ q.normal) < 1 - 1e-6 for p, q in zip(model.loading.plates, seed.loading.plates))
    assert model.loading.supports[0].mode == "sliding" and "rigid motion along it stopped" in model.loading.notes[0]
    np.testing.assert_array_equal(model.materials.mu, seed.materials.mu)  # a skin is the truth mesh's elements
    np.testing.assert_array_equal(unloaded.imaged_gravity, [0, -9.81, 0])
    with_effects = run_case(model, SolverSettings(device="cpu", relaxation=relaxation, unloaded=unloaded))
    plain = run_case(seed, SolverSettings(device="cpu", relaxation=relaxation))
    assert with_effects.ok and plain.ok, with_effects.solution.message
    assert with_effects.model.prestate is not None and with_effects.reference_state["residual_mm"] <= 0.02
    assert with_effects.reference_state["iterations"] >= 2
    assert np.abs(with_effects.displacement - plain.displacement).max() > 0.5
    assert TruthModel().hidden_effects == []
    for bad, match in (({"friction": -1}, "friction"), ({"gravity": [0, 1]}, "three finite"),
                       ({"compression_gravity": [0, 0, -9.81]}, "needs the gravity"),
                       ({"chest_wall": "glued"}, "fixed, sliding or elastic"), ({"skin": [5e4, 9]}, "thickness")):
        with pytest.raises(ValueError, match=match):
            TruthModel(**bad)


def test_a_truth_may_give_each_plate_its_own_friction():
    from BreastBiomechLib.phantom.compressed import TruthModel, with_hidden_effects
    from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression

    seed = hemi_ellipsoid_compression(10.0)
    truth = TruthModel(friction=[0.8, 0.0])
    assert truth.hidden_effects == ["friction per plate [0.8, 0.0]"]
    model, _ = with_hidden_effects(seed, truth)
    assert [p.friction for p in model.loading.plates] == [0.8, 0.0]
    assert TruthModel(friction=0.3).plate_frictions(2) == [0.3, 0.3]
    with pytest.raises(ValueError, match="3 plate frictions for 2 plates"):
        with_hidden_effects(seed, TruthModel(friction=[0.1, 0.2, 0.3]))
    for bad in ([0.5, -0.1], [], [[0.1]], [0.2, float("nan")]):
        with pytest.raises(ValueError, match="one such number per plate"):
            TruthModel(friction=bad)


def test_hidden_effect_options_need_a_compressed_case(tmp_path, capsys):
    from BreastBiomechLib.cli import main

    assert main(["phantom", "--out", str(tmp_path / "p"), "--friction", "0.5", "--no-overview"]) == 2
    assert "--friction change the truth simulation of a compressed case: add --compressed" in capsys.readouterr().err
    assert main(["phantom", "--out", str(tmp_path / "p"), "--chest-clearance-mm", "8", "--no-overview"]) == 2
    assert "--chest-clearance-mm change the truth simulation" in capsys.readouterr().err
    for option in ("--friction", "--chest-clearance-mm"):
        with pytest.raises(SystemExit) as stop:
            main(["phantom", "--out", str(tmp_path / "p"), option, "-1", "--compressed"])
        assert stop.value.code == 2 and "must be a finite number >= 0" in capsys.readouterr().err
