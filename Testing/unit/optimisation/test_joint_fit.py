"""Cases with several measured states: the phantom makes further states (`phantom --compressed
--state ...`), `optimise` fits every state of a case jointly (one set of materials, each state its
own plates, image and landmarks), and a joint fit of two copies of one state is that state's fit."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from BreastBiomechLib.io.case_layout import CaseLayout, read_force
from BreastBiomechLib.phantom.states import StateSpec, parse_state


def test_a_state_is_read_from_its_name_and_settings():
    assert parse_state(["lateral", "moving-plate=second", "compression=0.3", "force-sd=0.5"]) == \
        StateSpec("lateral", compression=0.3, moving_plate="second", force_sd=0.5)
    assert parse_state(["supine", "compression-gravity=0,0,-9.81", "axis=SI"]) == \
        StateSpec("supine", axis="SI", compression_gravity=(0.0, 0.0, -9.81))
    for words, message in ((["compressed"], "not 'compressed'"), (["bad name"], "letters, digits"),
                           (["s", "compression=0.8"], "between 0 and 0.7"), (["s", "axis=AP"], "one of LR, SI"),
                           (["s", "moving-plate=left"], "one of both, first, second"),
                           (["s", "compression-gravity=0,9.81"], "three finite numbers"),
                           (["s", "force-sd=-1"], "positive number of newtons"), (["s", "travel=3"], "not a setting"),
                           (["s", "axis=LR", "axis=SI"], "given twice"), ([], "needs a name")):
        with pytest.raises(ValueError, match=message):
            parse_state(words)


def test_a_state_needs_a_compressed_case_and_a_name_of_its_own(two_state_case, tmp_path, capsys):
    from BreastBiomechLib.cli import main

    assert main(["phantom", "--out", str(tmp_path / "p"), "--state", "lateral", "compression=0.3"]) == 2
    assert "add --compressed" in capsys.readouterr().err and not (tmp_path / "p").exists()
    assert main(["phantom-state", str(two_state_case), "--state", "lateral", "compression=0.3"]) == 2
    assert "holds the state lateral already" in capsys.readouterr().err
    assert main(["phantom-state", str(two_state_case), "--state", "a", "--state", "a"]) == 2
    assert "given more than once" in capsys.readouterr().err


def test_a_phantom_with_a_further_state_is_fitted_jointly(two_state_case, tmp_path, capsys):
    """conftest's two-state phantom (25 % by both plates and, as its state "lateral", 35 % by the
    second plate alone with the plate force recorded) fitted jointly on a coarse mesh of its
    labels (on purpose: the test is of the states, not of the segmentation). The further state
    is a truth of its own, the same breast and materials; the joint objective is the states'
    mean, and each state gets its outputs."""
    from BreastBiomechLib.cli import main
    from BreastBiomechLib.io.images import read_image
    from BreastBiomechLib.io.meshes import write_vtu
    from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels
    from BreastBiomechLib.phantom.truth_files import read_truth

    case = two_state_case
    layout = CaseLayout(case)
    assert [s.name for s in layout.check()] == ["compressed", "lateral"]
    first, lateral = read_truth(case)["truth"], read_truth(case, "lateral")["truth"]
    assert (lateral["compression"], lateral["moving_plate"]) == (0.35, "second")
    assert lateral["materials"] == first["materials"] and lateral["seed"] != first["seed"]
    force = read_force(layout.state("lateral"))
    assert force.sd == 0.5 and force.newtons > 0 and force.plate == json.loads(
        layout.state("lateral").plates.read_text())["plates"][1]["name"]
    mesh = mesh_labels(read_image(case / "labels.nrrd"), MeshSettings(edge_mm=12.0, refine_interfaces=False)).mesh
    write_vtu(tmp_path / "fitting.vtu", mesh)
    out = tmp_path / "fit"
    assert main(["optimise", str(case), "--model", "iso-hetero", "--free", "E", "--budget", "3", "--mesh",
                 str(tmp_path / "fitting.vtu"), "--device", "cpu", "--tolerance-mm", "0.05", "--out", str(out),
                 "--json", "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    best = summary["best"]
    assert set(best["states"]) == {"compressed", "lateral"}
    # the lateral state's measured plate force fixes the moduli's scale (force_scale.json)
    scale = summary["force_scale"]
    assert scale == json.loads((out / "force_scale.json").read_text())
    record = scale["states"]["lateral"]
    assert set(scale["states"]) == {"lateral"} and record["plate"] == force.plate
    assert scale["scale"] * record["predicted_N"] == pytest.approx(force.newtons)
    assert scale["sd"] == pytest.approx(force.sd / record["predicted_N"])
    assert scale["materials"]["glandular"]["E"] == pytest.approx(scale["scale"] * summary["materials"]["glandular"]["E"])
    assert best["objective"] == pytest.approx(np.mean([s["objective"] for s in best["states"].values()]))
    for name in ("predicted.nrrd", "predicted_landmarks.mrk.json", "deformed_mesh.vtu", "landmark_errors.json"):
        assert (out / name).is_file() and (out / "states" / "lateral" / name).is_file(), name
    assert read_image(out / "states" / "lateral" / "predicted.nrrd").GetSize() == \
        read_image(layout.state("lateral").mr).GetSize()
    recorded = json.loads((out / "case.json").read_text())
    assert set(recorded["states"]) == {"compressed", "lateral"} and recorded["fingerprint"] == recorded["states"]["compressed"]
    # resumed with other states: refused (its evaluations are of the two)
    assert main(["optimise", str(case), "--model", "iso-hetero", "--free", "E", "--budget", "4", "--mesh",
                 str(tmp_path / "fitting.vtu"), "--device", "cpu", "--tolerance-mm", "0.05", "--out", str(out),
                 "--states", "compressed", "--resume", "--quiet"]) == 2
    assert "cannot resume a fit of the states compressed, lateral with compressed" in capsys.readouterr().err
    # a state the case does not hold, and the plates' offsets with several states, refused
    assert main(["optimise", str(case), "--model", "iso-hetero", "--free", "E", "offset", "--budget", "2", "--mesh",
                 str(tmp_path / "fitting.vtu"), "--device", "cpu", "--out", str(tmp_path / "offsets"), "--quiet"]) == 2
    assert "without 'offset' free" in capsys.readouterr().err
    assert main(["optimise", str(case), "--states", "compressed", "mlo", "--budget", "2", "--mesh",
                 str(tmp_path / "fitting.vtu"), "--device", "cpu", "--out", str(tmp_path / "unknown"), "--quiet"]) == 2
    assert "no measured state 'mlo'" in capsys.readouterr().err


def test_a_joint_fit_of_two_copies_of_one_state_is_that_state_s_fit(compressed_case_dir, tmp_path):
    """The conftest's compressed case with its first state copied as a second: every parameter
    set's joint objective, NMI and landmark errors are the single state's."""
    from BreastBiomechLib.io.images import read_image
    from BreastBiomechLib.io.markups import read_markups
    from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels
    from BreastBiomechLib.optimisation import FittingProblem, ParameterSpace
    from BreastBiomechLib.optimisation.states import JointProblem
    from BreastBiomechLib.phantom.compressed_files import read_compressed
    from BreastBiomechLib.solver import DynamicRelaxation

    case = Path(shutil.copytree(compressed_case_dir, tmp_path / "case"))
    copy = case / "states" / "again"
    copy.mkdir(parents=True)
    for name in ("mr.nrrd", "landmarks.mrk.json", "plates.json"):
        shutil.copy(case / "compressed" / name, copy / name)
    mesh = mesh_labels(read_image(case / "labels.nrrd"), MeshSettings(edge_mm=12.0, refine_interfaces=False)).mesh
    tissues = np.unique(np.asarray(mesh.cell_data["tissue"]).astype(int))
    space = ParameterSpace.for_model("iso-hetero", tissues, free=("E",))
    undeformed, reference = read_image(case / "mr.nrrd"), read_markups(case / "landmarks.mrk.json")
    relaxation = DynamicRelaxation(tolerance_mm=0.05)

    def problem(state):
        m = read_compressed(case, state)
        return FittingProblem(space, mesh, undeformed, m.image, m.plates, landmarks=(reference, m.landmarks),
                              relaxation=relaxation, device="cpu")

    single, joint = problem("compressed"), JointProblem({"compressed": problem("compressed"), "again": problem("again")})
    z = np.full((1, space.dimension), 0.4)
    alone, together = single.evaluate(z)[0], joint.evaluate(z)[0]
    assert together.status == alone.status == "completed"
    for key in ("objective", "nmi", "ncc", "landmark_mean_mm", "landmark_max_mm"):
        assert getattr(together, key) == pytest.approx(getattr(alone, key), rel=1e-6), key
    assert together.states["again"] == together.states["compressed"]
    with pytest.raises(ValueError, match="at least two measured states"):
        JointProblem({"compressed": single})
