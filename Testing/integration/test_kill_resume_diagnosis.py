"""Kill and resume of a diagnosis: killed with SIGKILL at its checkpoints and run again with
--resume, it ends with exactly what an uninterrupted run writes (the CPU is deterministic), and no
half-written file is left. Kill points: Testing/support/kill_resume.py.
"""

from __future__ import annotations

import json
import re

import pytest
from kill_resume import assert_resumes_through_checkpoints, run


def without_wall_times(value):
    """A diagnosis record less its wall times (every key ending in "seconds")."""
    if isinstance(value, dict):
        return {k: without_wall_times(v) for k, v in value.items() if not k.endswith("seconds")}
    if isinstance(value, list):
        return [without_wall_times(v) for v in value]
    return value


def diagnosis_outputs(out) -> dict:
    """What a diagnosis wrote, less its wall times; NaN (a candidate that cannot be tested) is
    written as text so that two equal records compare equal."""
    import SimpleITK as sitk

    outputs = {name: json.dumps(without_wall_times(json.loads((out / name).read_text())), sort_keys=True)
               for name in ("diagnosis.json", "round-1.json")}
    outputs["report.md"] = re.sub(r"; \d+ s\.", "; (wall time) s.", (out / "report.md").read_text())
    for field in sorted(out.glob("round-*-residual-*.nrrd")):
        outputs[field.name] = sitk.GetArrayFromImage(sitk.ReadImage(str(field))).tobytes()
    outputs["files"] = sorted(p.name for p in out.iterdir() if p.name != "round-1-residual.png")
    return outputs


# the diagnosis's checkpoints, as its progress reports them: after the round's solves and statistics
# and before its first write (the residual field), and between the round's two writes (the field
# after the refit). Atomic writes themselves: Testing/integration/test_kill_resume.py.
CHECKPOINTS = ["round 1: residual displacement field (deformable registration)",
               "round 1: residual displacement field after adding friction"]
# what the run resumed after the first kill says: it takes the round's solves and statistics from
# the checkpoint the killed run kept, rather than making them again
TAKEN_UP = ["round 1: its solves and statistics taken from the interrupted run's checkpoint"]


@pytest.mark.slow
def test_a_diagnosis_killed_at_each_checkpoint_resumes_to_the_uninterrupted_result(friction_case, tmp_path):
    """The hidden-friction case (conftest's small one): one round that names friction (its one
    candidate: the other effects' solves would only lengthen every trial), adds it and refits
    (the confirmation refit, not refined); one run is killed before the round is written (its
    resume takes the round's solves up from the checkpoint kept before the registration), then,
    resumed, after the refit (its resume adds the effect to the open round from the round's kept
    diagnosis). The fixed floor and the linearised interval: the
    measured floor's solve and the profile's (tested in test_discrepancy.py and
    the Breast Discrepancy module's test) would lengthen every killed run."""
    case, fit = friction_case

    def diagnosis(out, resume=False, progress=False):
        return ["diagnose", str(case), "--fit", str(fit), "--out", str(out), "--effects", "friction",
                "--rounds", "1", "--refine-iterations", "0", "--device", "cpu", "--floor", "fixed",
                "--interval", "linearised",
                *([] if progress else ["--quiet"]), *(["--resume"] if resume else [])]

    run(diagnosis(tmp_path / "reference"))
    reference = diagnosis_outputs(tmp_path / "reference")
    assert "round-1-residual-after.nrrd" in reference["files"], "the reference run added no effect"
    assert_resumes_through_checkpoints(reference, diagnosis, diagnosis_outputs, tmp_path, CHECKPOINTS, TAKEN_UP)
