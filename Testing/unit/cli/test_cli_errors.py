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
    ("--compression", "0.9", "compression is a fraction of the breast's thickness in (0, 0.7], not 0.9"),
    ("--fit-budget", "5", "the fit's budget (5 solves) must hold one generation of 12"),
    ("--fit-population", "1", "the fit's population needs at least 2 models, not 1"),
])
def test_suite_settings_are_checked_before_a_run_records_them(tmp_path, capsys, option, value, message):
    out = tmp_path / "suite"
    assert main(["discrepancy-suite", "--out", str(out), option, value, "--workers", "0"]) == 2
    assert message in _error_line(capsys)
    assert not (out / "settings.json").exists()  # a later run with good settings is not refused


def test_suite_settings_refuse_what_no_case_could_be_made_with():
    from BreastBiomechLib.discrepancy.suite import SuiteSettings

    with pytest.raises(ValueError, match=r"suite settings: .*at least one round.*landmark_noise_mm must be >= 0"):
        SuiteSettings(rounds=0, landmark_noise_mm=-1.0)


def test_a_study_checks_its_cases_before_starting_a_cluster(tmp_path, capsys):
    missing = tmp_path / "no-such-case"
    assert main(["study", str(missing), "--out", str(tmp_path / "study")]) == 2
    assert _error_line(capsys).endswith(f"{missing}: not a compressed case (no plates.json); make one with "
                                        "`breastbiomech phantom --case N --compressed --out DIR`")
    assert not (tmp_path / "study").exists()


def _numeric_options():
    """(command words, option, argparse type, how many values) of every option of every command
    that takes numbers."""
    from BreastBiomechLib.cli import build_parser
    from BreastBiomechLib.cli import common

    numeric = {common.finite, common.positive, common.fraction, common.positive_int, common.non_negative_int,
               common.non_negative, int, float}
    found = []

    def walk(words, parser):
        for action in parser._actions:
            if action.__class__.__name__ == "_SubParsersAction":
                for name, sub in action.choices.items():
                    walk(words + [name], sub)
            elif action.option_strings and action.type in numeric and not action.choices:
                count = action.nargs if isinstance(action.nargs, int) else 1
                found.append((words, action.option_strings[-1], action.type, count))
    walk([], build_parser())
    return found


def test_every_numeric_option_is_checked_by_the_parser():
    """Plain int or float lets NaN, infinities and out-of-range numbers through to where they
    fail late (or not at all); every number a command takes has a checked type."""
    plain = [f"{' '.join(words)} {option}" for words, option, kind, _ in _numeric_options() if kind in (int, float)]
    assert not plain, f"options without a checked number type: {plain}"
    assert len(_numeric_options()) > 80


@pytest.mark.parametrize("words, option, kind, count", _numeric_options(),
                         ids=lambda v: v if isinstance(v, str) else None)
def test_a_number_out_of_range_is_refused_with_the_option_named(capsys, words, option, kind, count):
    from BreastBiomechLib.cli import common

    bad = "nan" if kind in (common.finite, common.positive, common.fraction, common.non_negative) else "-1"
    with pytest.raises(SystemExit) as stop:
        main(words + [option] + [bad] * count)
    assert stop.value.code == 2
    line = _error_line(capsys)
    assert f"argument {option}: must be " in line and bad in line


def test_the_demos_meshes_default_to_the_devices_and_take_the_sizes_given():
    """`demo --truth-edge-mm/--fit-edge-mm/--budget` (and `bench demo`'s, whose suite defaults do
    not apply to it): the device's meshes unless given; the fitting mesh's skin at the device's
    ratio; nonsense refused."""
    from BreastBiomechLib.cli.demo import DemoMeshes

    gpu, cpu = DemoMeshes.for_device(True), DemoMeshes.for_device(False)
    assert (gpu.truth_edge_mm, gpu.fit_edge_mm, gpu.fit_skin_mm, gpu.refine_interfaces, gpu.budget) == (2.0, 4.0, 2.0,
                                                                                                       True, 200)
    assert (cpu.truth_edge_mm, cpu.fit_edge_mm, cpu.fit_skin_mm, cpu.refine_interfaces, cpu.budget) == (6.0, 5.0, 5.0,
                                                                                                       False, 19)
    like_cpu = DemoMeshes.for_device(True, truth_edge_mm=3.0, fit_edge_mm=5.0)
    assert (like_cpu.truth_edge_mm, like_cpu.fit_edge_mm, like_cpu.fit_skin_mm, like_cpu.budget) == (3.0, 5.0, 2.5, 200)
    assert like_cpu.spacing_mm == gpu.spacing_mm and like_cpu.blur_mm == gpu.blur_mm
    with pytest.raises(ValueError, match="fit_edge_mm must be positive, not -4"):
        DemoMeshes.for_device(False, fit_edge_mm=-4.0)


@pytest.mark.parametrize("argv, message", [(["demo", "--fit-edge-mm", "0"], "--fit-edge-mm"),
                                           (["bench", "demo", "--truth-edge-mm", "-2"], "--truth-edge-mm")])
def test_the_demos_mesh_options_are_checked_by_the_parser(capsys, argv, message):
    with pytest.raises(SystemExit):
        main(argv)
    assert message in capsys.readouterr().err
