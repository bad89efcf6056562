"""``--progress json``: while a command runs its standard output carries only its events, one
JSON object per line (BreastBiomechLib/cli/events.py), which the Slicer panels read from a
command run out of their process; the report for people goes to standard error."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from BreastBiomechLib.cli import main

sys.path.insert(0, __file__.rsplit("/unit/", 1)[0] + "/unit/io")
from test_simulate_case import _case  # noqa: E402  (the small block case of the case-file tests)


def _events(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines()]


def test_a_command_writes_its_events_and_nothing_else_on_standard_output(tmp_path, capsys):
    path, _, _ = _case(tmp_path)
    assert main(["simulate", str(path), "--out", str(tmp_path / "out"), "--progress", "json"]) == 0
    out, err = capsys.readouterr()
    events = _events(out)  # every line an event
    assert events[0]["event"] == "start" and events[0]["command"] == "simulate"
    assert events[-1]["event"] == "done" and events[-1]["exit"] == 0
    assert events[-1]["outputs"]["solution"] == str(tmp_path / "out" / "solution.json")
    progress = [e for e in events if e["event"] == "progress"]
    fractions = [e["fraction"] for e in progress]
    assert len(progress) > 3 and fractions == sorted(fractions) and fractions[0] == 0.0 and fractions[-1] == 1.0
    assert "on the CPU" in progress[0]["message"]
    seconds = [e["seconds"] for e in events]
    assert seconds == sorted(seconds)
    assert "completed" in err and "written:" in err  # the report, for people, on standard error
    assert sys.stdout is not None and "simulate" not in capsys.readouterr().out  # standard output given back


def test_a_failing_command_ends_with_its_error_event(tmp_path, capsys):
    path = tmp_path / "case.json"
    path.write_text("{")
    assert main(["simulate", str(path), "--out", str(tmp_path / "out"), "--progress", "json"]) == 2
    out, err = capsys.readouterr()
    events = _events(out)
    assert [e["event"] for e in events] == ["start", "error"]
    assert events[-1]["exit"] == 2 and "case.json" in events[-1]["message"]
    assert events[-1]["message"] in err


@pytest.mark.parametrize("command", ["simulate", "optimise", "diagnose"])
def test_the_long_commands_offer_json_progress(command, capsys):
    with pytest.raises(SystemExit):
        main([command, "--help"])
    assert "--progress {bar,json,none}" in capsys.readouterr().out


def test_the_library_runs_as_a_module():
    done = subprocess.run([sys.executable, "-m", "BreastBiomechLib", "--version"], capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.startswith("breastbiomech ")
