"""The case folder's layout (issue 78 point 1): one module knows where each file lies, further
measured states are found and validated with errors that name the file and what to do, and the
phantom's truth files sit behind a reader the fit and the diagnosis never import."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from BreastBiomechLib.io.case_layout import CaseLayout, CaseLayoutError, PlateForce, read_force
from BreastBiomechLib.io.markups import write_markups
from BreastBiomechLib.landmarks import Landmarks

PLATES = {"axis": "LR", "compression": 0.3, "gravity": [0.0, -9.81, 0.0],
          "plates": [{"name": "right", "point": [-30.0, 0.0, 0.0], "normal": [1.0, 0.0, 0.0]},
                     {"name": "left", "point": [30.0, 0.0, 0.0], "normal": [-1.0, 0.0, 0.0]}]}


def _state(folder: Path, landmarks: bool) -> None:
    folder.mkdir(parents=True)
    sitk.WriteImage(sitk.Image(4, 4, 4, sitk.sitkFloat32), str(folder / "mr.nrrd"))
    (folder / "plates.json").write_text(json.dumps(PLATES))
    if landmarks:
        write_markups(folder / "landmarks.mrk.json", Landmarks(np.zeros((1, 3)), ["L01"]))


def _case(root: Path, landmarks: bool = True) -> CaseLayout:
    root.mkdir()
    sitk.WriteImage(sitk.Image(4, 4, 4, sitk.sitkFloat32), str(root / "mr.nrrd"))
    if landmarks:
        write_markups(root / "landmarks.mrk.json", Landmarks(np.zeros((1, 3)), ["L01"]))
    _state(root / "compressed", landmarks)
    return CaseLayout(root)


def test_a_single_scan_case_is_one_state_and_further_states_are_found_in_name_order(tmp_path):
    layout = _case(tmp_path / "case")
    assert [s.name for s in layout.check()] == ["compressed"] and layout.unused_states_note() == ""
    assert layout.state().mr == tmp_path / "case" / "compressed" / "mr.nrrd"
    _state(tmp_path / "case" / "states" / "mlo", landmarks=True)
    _state(tmp_path / "case" / "states" / "cc-20pc", landmarks=True)
    states = layout.check()
    assert [s.name for s in states] == ["compressed", "cc-20pc", "mlo"]
    assert states[2].plates == tmp_path / "case" / "states" / "mlo" / "plates.json"
    note = layout.unused_states_note(why="the diagnosis stacks no further states yet")
    assert "states/cc-20pc, states/mlo" in note and "it uses compressed/ only; the diagnosis stacks" in note
    assert layout.unused_states_note(["compressed", "mlo"]).startswith(f"{layout.root} holds measured states this "
                                                                        "run does not use (states/cc-20pc)")
    assert layout.unused_states_note(["compressed", "cc-20pc", "mlo"]) == ""


@pytest.mark.parametrize("damage, message", [
    (lambda root: (root / "mr.nrrd").unlink(), "no undeformed MR"),
    (lambda root: (root / "states").write_text("x"), "is a file: states/ holds one folder"),
    (lambda root: ((root / "states").mkdir(), (root / "states" / "notes.txt").write_text("x")), "not files"),
    (lambda root: _state(root / "states" / "bad name", True), "letters, digits"),
    (lambda root: (_state(root / "states" / "second", True), (root / "states" / "second" / "plates.json").unlink()),
     "state 'second': no plates.json"),
    (lambda root: _state(root / "states" / "second", False), "no landmarks"),
])
def test_a_damaged_case_folder_is_refused_naming_the_file_and_what_to_do(tmp_path, damage, message):
    layout = _case(tmp_path / "case")
    damage(layout.root)
    with pytest.raises((CaseLayoutError, FileNotFoundError), match=re.escape(message)):
        layout.check()


def test_a_measured_plate_force_is_read_and_a_bad_one_named(tmp_path):
    layout = _case(tmp_path / "case")
    state = layout.state()
    state.force.write_text(json.dumps({"newtons": 14.2, "sd": 1.5, "plate": "left"}))
    assert read_force(state) == PlateForce(14.2, 1.5, "left")
    assert layout.check()  # a valid force record passes the folder's check
    for record, message in [("{not json", "not readable as JSON"), ('{"newtons": -3, "sd": 1}', "positive number"),
                            ('{"newtons": 3}', "sd must be"), ('{"newtons": 3, "sd": 1, "unit": "N"}', "unknown keys"),
                            ('{"newtons": 3, "sd": 1, "plate": "top"}', "one of the state's plates"), ("[3, 1]", "object")]:
        state.force.write_text(record)
        with pytest.raises(CaseLayoutError, match=re.escape(message)):
            read_force(state)
        with pytest.raises(CaseLayoutError, match=re.escape(message)):
            layout.check()


def test_the_fit_and_the_diagnosis_never_import_the_truth_reader():
    """No inverse crime: the phantom's truth files are read through phantom.truth_files only, which
    the diagnosis, its effects and the fit never import; the cohort study reads it to score its
    table after a fit has answered."""
    library = Path(__file__).resolve().parents[3] / "BreastBiomechLib"
    guarded = [*(library / "discrepancy").glob("*.py"), *(library / "discrepancy" / "effects").glob("*.py"),
               *(library / "optimisation").glob("*.py")]
    readers = sorted(p.name for p in guarded if "truth_files" in re.sub(r'"""[\s\S]*?"""', "", p.read_text()))
    assert readers == ["study.py"], readers
    # and the layout module knows every case file's name: the fit and the diagnosis name none themselves
    for path in guarded:
        code = re.sub(r'"""[\s\S]*?"""', "", path.read_text())
        assert '"mr.nrrd"' not in code and '"plates.json"' not in code, path
