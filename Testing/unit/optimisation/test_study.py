"""The four-model study (BreastBiomechLib.optimisation.study, `breastbiomech study`): which truths
lie in which model family, the report's tables and recovery figures, the Markdown file's prose
kept around the tables, and the command end to end on the compressed test phantom with resume."""

from __future__ import annotations

import json

import pytest

from BreastBiomechLib.optimisation.study import (
    MARKERS,
    StudyFit,
    StudySettings,
    best_fits,
    device_name,
    recovery,
    study_markdown,
    truth_in_family,
    write_report,
)

ISOTROPIC_TRUTH = {"fat": {"E": 10e3, "nu": 0.495}, "glandular": {"E": 25e3, "nu": 0.495},
                   "muscle": {"E": 80e3, "nu": 0.495}}
TI_FAT_TRUTH = {**ISOTROPIC_TRUTH, "fat": {"E": 10e3, "nu": 0.495, "eta": 4e3, "fibre": [0.0, 0.0, 1.0]}}
SI = (0.0, 0.0, 1.0)


def test_truth_in_family():
    assert truth_in_family(ISOTROPIC_TRUTH, "iso-hetero", SI)
    assert truth_in_family(ISOTROPIC_TRUTH, "aniso-hetero", SI)  # eta at its 1 Pa lower bound
    assert not truth_in_family(ISOTROPIC_TRUTH, "iso-homo", SI)  # three different materials
    assert not truth_in_family(TI_FAT_TRUTH, "iso-hetero", SI)
    assert truth_in_family(TI_FAT_TRUTH, "aniso-hetero", SI)
    assert not truth_in_family(TI_FAT_TRUTH, "aniso-hetero", (1.0, 0.0, 0.0))  # fibres along another axis
    one = {name: {"E": 10e3, "nu": 0.49} for name in ("fat", "glandular")}
    assert truth_in_family(one, "iso-homo", SI)
    assert not truth_in_family({"fat": {"E": 12e3, "nu": 0.49}}, "iso-homo", SI)  # fat's E is the reference


def _row(case, model, optimiser, objective, error_mean, materials, in_family=True, truth=ISOTROPIC_TRUTH):
    stats = {"mean": error_mean, "sd": 0.5, "max": error_mean + 1.0}
    return StudyFit(case, model, optimiser, -objective, objective, 40, 1, 12.0, "budget",
                    {"landmarks": 17, "displacement_mm": {"mean": 9.0, "sd": 3.0, "max": 20.0}, "error_mm": stats},
                    materials, truth, in_family)


def _fitted(glandular_e, muscle_nu):
    return {"fat": {"E": 10e3, "nu": 0.494, "eta": 0.0}, "glandular": {"E": glandular_e, "nu": 0.495, "eta": 0.0},
            "muscle": {"E": 80e3, "nu": muscle_nu, "eta": 0.0}}


def test_best_fit_and_recovery():
    worse = _row("case2", "iso-hetero", "hybrid", -1.5, 4.0, _fitted(40e3, 0.47))
    better = _row("case2", "iso-hetero", "cmaes", -1.6, 2.0, _fitted(27.5e3, 0.49))
    assert best_fits([worse, better])[("case2", "iso-hetero")] is better
    errors = recovery(better)
    assert errors["glandular"]["E_rel"] == pytest.approx(0.1)
    assert errors["muscle"]["E_rel"] == pytest.approx(0.0)
    assert errors["muscle"]["nu_abs"] == pytest.approx(0.005)
    assert "E_rel" not in errors["fat"] and errors["fat"]["nu_abs"] == pytest.approx(0.001)
    homogeneous = _row("case2", "iso-homo", "cmaes", -1.4, 6.0, {"breast": {"E": 10e3, "nu": 0.49, "eta": 0.0}},
                       in_family=False)
    assert recovery(homogeneous) == {}


def test_markdown_tables():
    rows = [_row("case10", "iso-hetero", "cmaes", -1.6, 2.0, _fitted(27.5e3, 0.49)),
            _row("case10", "iso-hetero", "hybrid", -1.5, 4.0, _fitted(40e3, 0.47)),
            _row("case2", "iso-hetero", "cmaes", -1.7, 3.5, _fitted(25e3, 0.495)),
            _row("case2", "iso-homo", "cmaes", -1.4, 6.0, {"breast": {"E": 10e3, "nu": 0.49, "eta": 0.0}},
                 in_family=False)]
    text = study_markdown(rows, StudySettings(models=("iso-hetero", "iso-homo"), optimisers=("cmaes", "hybrid")),
                          {"date": "2026-11-23", "device": "test"})
    lines = text.splitlines()
    table2 = [line for line in lines if line.startswith("| case2 |") or line.startswith("| case10 |")]
    # cases in natural order (case2 before case10), the better optimiser's fit, in-family marked
    assert table2[0].startswith("| case2 | 9.00 ± 3.00 (20.0) | 3.50 ± 0.50 (4.5)* | 6.00 ± 0.50 (7.0) |")
    assert table2[1].startswith("| case10 | 9.00 ± 3.00 (20.0) | 2.00 ± 0.50 (3.0)* | - |")
    assert "|  | glandular | 27.5 [25] | 0.4950 [0.4950] | - |  |  |  |" in text  # kPa, truth in brackets
    assert "| case10 | iso-hetero | 10.0% (glandular) | 0.0050 | 2.00 (3.00) | yes |" in text
    assert "| case2 | iso-hetero | 0.0% (glandular) | 0.0010 | 3.50 (4.50) | no |" in text  # 3.5 > 2.87 mm
    assert "### Optimisers on the same fits" in text
    assert "| case10 | iso-hetero | hybrid | 1.5000 | 40 (1) | 12 | budget |" in text
    assert "Solved on" not in text  # rows from before devices were recorded claim none
    rows[0].device = rows[1].device = "GPU A"
    text = study_markdown(rows, StudySettings(models=("iso-hetero", "iso-homo")), {"date": "2026-11-23"})
    assert "Solved on: GPU A (2 fits); device not recorded (2 fits). " in text
    assert "Fits: hybrid, cmaes;" in text  # the optimisers of the rows, also those another run fitted


def test_report_keeps_the_prose_around_the_tables(tmp_path):
    path = tmp_path / "validation.md"
    write_report(path, "first tables")
    assert path.read_text() == f"{MARKERS[0]}\nfirst tables\n{MARKERS[1]}\n"
    path.write_text("# Validation\n\nWhy and how.\n\n" + path.read_text() + "\nWhat it shows.\n")
    write_report(path, "second tables\n")
    assert path.read_text() == f"# Validation\n\nWhy and how.\n\n{MARKERS[0]}\nsecond tables\n{MARKERS[1]}\n\nWhat it shows.\n"


def test_settings_refuse_what_they_cannot_fit():
    with pytest.raises(ValueError, match="choose models"):
        StudySettings(models=("iso",))
    with pytest.raises(ValueError, match="choose optimisers"):
        StudySettings(optimisers=("newton",))
    with pytest.raises(ValueError, match="at least one forward solve"):
        StudySettings(budgets={"iso-homo": 0})


@pytest.mark.slow
def test_the_command_fits_resumes_and_reports(compressed_case_dir, tmp_path, capsys):
    """`breastbiomech study` on the compressed test phantom: one model, a few solves, a coarse
    fitting mesh; rerun with a second optimiser it replays the first fit and adds the second."""
    from BreastBiomechLib.cli import main

    report = tmp_path / "validation.md"
    report.write_text("# Validation\n\nProse that stays.\n")
    out = tmp_path / "study"
    arguments = ["study", str(compressed_case_dir), "--out", str(out), "--models", "iso-homo", "--budget",
                 "iso-homo=2", "--edge-mm", "10", "--device", "cpu", "--tolerance-mm", "0.05", "--report",
                 str(report), "--quiet"]
    assert main(arguments) == 0
    rows = json.loads((out / "study.json").read_text())["fits"]
    assert [(r["case"], r["model"], r["optimiser"], r["evaluations"]) for r in rows] == [
        ("case", "iso-homo", "cmaes", 2)]
    assert rows[0]["in_family"] is False and 1.0 < rows[0]["nmi"] < 2.0
    assert rows[0]["landmark_errors"]["error_mm"]["mean"] > 0
    assert rows[0]["device"] == device_name("cpu")
    assert set(rows[0]["truth"]) >= {"fat", "glandular", "muscle"}
    assert (out / "case" / "fitting_mesh.vtu").is_file()
    assert (out / "case" / "iso-homo-cmaes" / "predicted.nrrd").is_file()
    text = report.read_text()
    assert text.startswith("# Validation\n\nProse that stays.\n") and MARKERS[0] in text
    assert "breastbiomech study" in text and "| case |" in text and f"Solved on: {device_name('cpu')} (1 fit)" in text
    capsys.readouterr()

    first = (out / "case" / "iso-homo-cmaes" / "evaluations.jsonl").read_text()
    assert main(arguments[:-1] + ["--optimisers", "cmaes", "hybrid", "--quiet"]) == 0
    assert (out / "case" / "iso-homo-cmaes" / "evaluations.jsonl").read_text() == first  # replayed, no new solve
    rows = json.loads((out / "study.json").read_text())["fits"]
    assert sorted(r["optimiser"] for r in rows) == ["cmaes", "hybrid"]
    assert "### Optimisers on the same fits" in report.read_text()

    assert main(arguments[:-1] + ["--budget", "iso-homo=lots"]) == 2
    assert "MODEL=SOLVES" in capsys.readouterr().err


def test_a_study_fit_reads_the_truth_only_after_the_fit():
    """No inverse crime: the study task reads the case's truth (for the report's truth columns)
    only after fit_compressed_case has returned; the fit itself runs on a case without its truth
    (test_optimisation)."""
    import ast
    import inspect

    from BreastBiomechLib.optimisation import study

    tree = ast.parse(inspect.getsource(study.fit_study_case))
    calls = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            name = node.func.id if isinstance(node.func, ast.Name) else getattr(node.func, "attr", "")
            calls.setdefault(name, node.lineno)
    assert calls["read_truth"] > calls["fit_compressed_case"]
