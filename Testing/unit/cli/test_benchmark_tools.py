"""benchmarks/compare_libraries.py: versions of the library exported from git and run in turn."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
SCRIPT = ROOT / "benchmarks" / "compare_libraries.py"


def _compare(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *argv], capture_output=True, text=True, cwd=ROOT,
                          timeout=600)


def test_versions_run_in_turn_each_from_its_own_copy(tmp_path):
    exported = _compare("--export", "HEAD", str(tmp_path / "base"))
    assert exported.returncode == 0, exported.stderr
    assert (tmp_path / "base" / "BreastBiomechLib" / "solver" / "tled.py").is_file()
    # a second export to the same folder would hide which version it holds: refused
    again = _compare("--export", "HEAD", str(tmp_path / "base"))
    assert again.returncode != 0 and "exists" in again.stderr

    done = _compare(f"base={tmp_path / 'base'}", "head=.", "--runs", "--tets 300", "--rounds", "2", "--device", "cpu")
    assert done.returncode == 0, done.stderr
    lines = [json.loads(line) for line in done.stdout.splitlines()]
    runs, summary = lines[:-1], lines[-1]
    assert [(r["version"], r["round"]) for r in runs] == [("base", 1), ("head", 1), ("base", 2), ("head", 2)]
    # the working tree and its last commit solve the same model to the same answer
    assert len({(r["steps"], r["plate_force_N"], r["max_displacement_mm"]) for r in runs}) == 1
    assert summary["run"] == "--tets 300" and summary["base"]["median_to_first"] == 1.0
    assert summary["head"]["us_per_step_per_model"] == [r["us_per_step_per_model"] for r in runs[1::2]]


def test_each_version_runs_its_own_source(tmp_path):
    """A copy whose bench compresses less is run as itself, not as the working tree's package."""
    assert _compare("--export", "HEAD", str(tmp_path / "less")).returncode == 0
    bench = tmp_path / "less" / "BreastBiomechLib" / "cli" / "bench.py"
    bench.write_text(bench.read_text().replace("compression=0.25", "compression=0.15"))
    done = _compare(f"less={tmp_path / 'less'}", "head=.", "--runs", "--tets 300", "--rounds", "1", "--device", "cpu")
    assert done.returncode == 0, done.stderr
    less, head = (json.loads(line) for line in done.stdout.splitlines()[:2])
    assert less["version"] == "less" and head["version"] == "head"
    assert less["plate_force_N"] < 0.8 * head["plate_force_N"]


@pytest.mark.parametrize("argv, message", [
    (["empty=EMPTY", "head=."], "holds no BreastBiomechLib"),
    (["head=."], "two versions or more"),
    (["a=.", "a=."], "two versions have one name"),
])
def test_bad_versions_are_named(tmp_path, argv, message):
    (tmp_path / "empty").mkdir()
    done = _compare(*[a.replace("EMPTY", str(tmp_path / "empty")) for a in argv], "--runs", "--tets 300",
                    "--device", "cpu")
    assert done.returncode != 0 and message in done.stderr
