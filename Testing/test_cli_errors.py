"""Bad arguments on the command line (issue 28, item 2): exit code 2 and one line that names the
problem, before anything runs or is written; never a traceback."""

from __future__ import annotations

import pytest

from BreastBiomechLib.cli import main


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert err and "Traceback" not in "\n".join(err)
    return err[-1]


@pytest.mark.parametrize("argv", [
    ["phantom", "--out", "OUT", "--device", "gpu"],
    ["simulate", "case.json", "--out", "OUT", "--device", "cuda0"],
    ["bench", "solver", "--device", "bogus"],
    ["optimise", "case", "--out", "OUT", "--device", "nvidia"],
    ["discrepancy-suite", "--out", "OUT", "--device", "cuda:x"],
    ["warp", "m.vtu", "u.npy", "mr.nrrd", "--out", "OUT", "--device", "GPU"],
])
def test_a_device_name_that_is_not_one_is_refused_by_the_parser(tmp_path, capsys, argv):
    argv = [str(tmp_path / a) if a in ("OUT", "case.json", "case", "m.vtu", "u.npy", "mr.nrrd") else a for a in argv]
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    assert "argument --device: takes cpu, cuda or cuda:K" in _error_line(capsys)
    assert not (tmp_path / "OUT").exists()


def test_an_output_folder_that_is_a_file_is_named_with_what_to_do(tmp_path, capsys):
    taken = tmp_path / "taken"
    taken.write_text("a file")
    assert main(["phantom", "--out", str(taken), "--volume-cm3", "450"]) == 2
    assert _error_line(capsys).endswith(f"{taken} is a file where a folder is needed; give another --out "
                                        "(a new or existing folder)")


@pytest.mark.parametrize("option, value, message", [
    ("--compression", "2", "compression is a fraction of the breast's thickness in (0, 0.7], not 2.0"),
    ("--fit-budget", "-1", "the fit's budget (-1 solves) must hold one generation of 12"),
    ("--fit-population", "1", "the fit's population needs at least 2 models, not 1"),
    ("--rounds", "0", "the diagnosis needs at least one round, not 0"),
    ("--truth-edge-mm", "0", "the truth and fitting meshes' edges must be positive (mm)"),
])
def test_suite_settings_are_checked_before_a_run_records_them(tmp_path, capsys, option, value, message):
    out = tmp_path / "suite"
    assert main(["discrepancy-suite", "--out", str(out), option, value, "--workers", "0"]) == 2
    assert message in _error_line(capsys)
    assert not (out / "settings.json").exists()  # a later run with good settings is not refused


def test_a_study_checks_its_cases_before_starting_a_cluster(tmp_path, capsys):
    missing = tmp_path / "no-such-case"
    assert main(["study", str(missing), "--out", str(tmp_path / "study")]) == 2
    assert _error_line(capsys).endswith(f"{missing}: not a compressed case (no plates.json); make one with "
                                        "`breastbiomech phantom --case N --compressed --out DIR`")
    assert not (tmp_path / "study").exists()
