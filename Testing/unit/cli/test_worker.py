"""The panels' worker (BreastBiomech/BreastBiomechCommon/worker.py): a `breastbiomech` command
in a child process whose events arrive while it runs, which a Cancel stops within its grace
period, and whose failures are told in the command's own words or by how it ended."""

from __future__ import annotations

import os
import signal
import sys
import time

import pytest

from BreastBiomechCommon.worker import CommandWorker

sys.path.insert(0, __file__.rsplit("/unit/", 1)[0] + "/unit/io")
from test_simulate_case import _case  # noqa: E402  (the small block case of the case-file tests)


def _running(tmp_path, total_time=30.0):
    """A worker solving the block case for ``total_time`` s of physical time (long enough to be
    running when the test acts), once its first progress event has arrived."""
    path, _, _ = _case(tmp_path, total_time=total_time, settle_time=0.0)
    worker = CommandWorker(["simulate", str(path), "--out", str(tmp_path / "out")], folder=str(tmp_path)).start()
    while worker.running and worker.last is None:
        worker.poll()
        time.sleep(0.02)
    assert worker.running, worker.error
    return worker


def test_events_arrive_while_the_command_runs_and_cancel_stops_it(tmp_path):
    worker = _running(tmp_path)
    assert worker.events[0]["event"] == "start" and worker.last["event"] == "progress"
    seconds = worker.cancel(grace_s=10.0)
    assert 0.0 < seconds < 10.0 and not worker.running and worker.cancelled
    assert worker.returncode != 0 and worker.error == "cancelled" and not worker.succeeded
    assert not (tmp_path / "out" / "solution.json").exists()  # nothing half-written
    assert worker.cancel() == 0.0  # ended already


def test_a_worker_killed_from_outside_says_how_it_ended(tmp_path):
    worker = _running(tmp_path)
    os.kill(worker.process.pid, signal.SIGKILL)  # what an out-of-memory kill does
    worker.wait(30)
    assert worker.returncode == -signal.SIGKILL
    assert worker.error.startswith("breastbiomech simulate stopped (killed by signal 9)")


def test_a_failing_command_gives_its_own_sentence(tmp_path):
    worker = CommandWorker(["simulate", str(tmp_path / "missing.json"), "--out", str(tmp_path / "out")]).start()
    assert worker.wait(60) == 2
    assert worker.error == f"breastbiomech simulate: error: {tmp_path / 'missing.json'}: no such case file"
    assert [e["event"] for e in worker.events] == ["start", "error"] and worker.outputs() == {}


def test_a_worker_is_started_once_with_a_command():
    with pytest.raises(ValueError, match="needs a command"):
        CommandWorker([])
    worker = CommandWorker(["--version"])
    assert worker.arguments == ["--version", "--progress", "json"]
