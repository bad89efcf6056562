"""Kill and resume: a fit and a study killed with SIGKILL at random moments and run again end
with exactly what an uninterrupted run writes (the CPU is deterministic), and no half-written
file is ever taken for a finished one (the diagnosis: test_kill_resume_diagnosis.py). Kill points:
Testing/support/kill_resume.py.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from kill_resume import assert_resumes_to, run


def fit_outputs(out) -> dict:
    """What a fit wrote, less what differs between any two runs (wall times, replay counts)."""
    import SimpleITK as sitk

    result = json.loads((out / "result.json").read_text())
    for key in ("seconds", "replayed"):
        result.pop(key)
    result["best"].pop("seconds")
    evaluations = [json.loads(line) for line in (out / "evaluations.jsonl").read_text().splitlines()]
    for evaluation in evaluations:
        evaluation.pop("seconds")
    predicted = sitk.GetArrayFromImage(sitk.ReadImage(str(out / "predicted.nrrd")))
    return {"result": result, "evaluations": evaluations, "predicted": predicted.tobytes(),
            "landmarks": (out / "landmark_errors.json").read_text(), "mesh": (out / "fitting_mesh.vtu").read_bytes()}



@pytest.mark.slow
def test_a_fit_killed_anywhere_resumes_to_the_uninterrupted_result(compressed_case_dir, tmp_path):
    def fit(out, resume=False):
        # the phantom's truth labels meshed on purpose: this test is of the fit's kill and resume
        return ["optimise", str(compressed_case_dir), "--out", str(out), "--model", "iso-homo", "--budget", "4",
                "--labels", str(compressed_case_dir / "labels.nrrd"),
                "--population", "2", "--edge-mm", "12", "--tolerance-mm", "0.05", "--device", "cpu", "--seed", "4",
                "--quiet", *(["--resume"] if resume else [])]

    seconds = run(fit(tmp_path / "reference"))
    reference = fit_outputs(tmp_path / "reference")
    assert_resumes_to(reference, seconds, fit, fit_outputs, tmp_path, salt=1)


@pytest.mark.slow
def test_a_study_killed_anywhere_resumes_to_the_uninterrupted_result(compressed_case_dir, tmp_path):
    from BreastBiomechLib.optimisation.study import read_study

    def study(out, resume=False):
        """The study resumes by running the same command again."""
        return ["study", str(compressed_case_dir), "--out", str(out), "--models", "iso-homo", "aniso-homo",
                "--budget", "iso-homo=2", "aniso-homo=2", "--edge-mm", "12", "--tolerance-mm", "0.05",
                "--device", "cpu", "--workers", "0", "--quiet"]

    def rows(out):
        return {"rows": sorted((r.case, r.model, r.optimiser, r.nmi, r.objective, r.evaluations, r.failed, r.stopped,
                       json.dumps(r.materials, sort_keys=True)) for r in read_study(out))}

    seconds = run(study(tmp_path / "reference"))
    reference = rows(tmp_path / "reference")
    assert len(reference["rows"]) == 2
    assert_resumes_to(reference, seconds, study, rows, tmp_path, salt=2)


def test_a_write_that_fails_leaves_the_old_file_and_no_partial_one(tmp_path):
    """Atomic writes: a writer that dies half way leaves the previous file whole and no temporary."""
    from BreastBiomechLib.io.atomic import atomic_path, write_json_atomically

    path = write_json_atomically(tmp_path / "out" / "result.json", {"nmi": 1.2, "e": np.float64(3.0)})
    with pytest.raises(RuntimeError), atomic_path(path) as temporary:
        temporary.write_text('{"nmi": 1.')
        raise RuntimeError("killed mid-write")
    assert json.loads(path.read_text()) == {"nmi": 1.2, "e": 3.0}
    assert sorted(p.name for p in path.parent.iterdir()) == ["result.json"]
