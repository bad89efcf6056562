"""A second process pointed at an output folder a run is writing is refused; a run that was
killed leaves a claim the next run takes over (issue 28: two processes on one folder; kill and
resume)."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys

import pytest

from BreastBiomechLib.io.claims import CLAIM_FILE, FolderInUse, claimed


def _claim_of(folder, pid, host=None):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / CLAIM_FILE).write_text(json.dumps({"pid": pid, "host": host or socket.gethostname(),
                                                 "what": "a study", "started": "2026-11-25 12:00:00"}))


def test_a_folder_held_by_a_live_process_is_refused_with_who_holds_it(tmp_path):
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        _claim_of(tmp_path / "out", other.pid)
        with pytest.raises(FolderInUse, match=rf"in use by a study \(process {other.pid} on .*\): wait for it to "
                                              r"end or give another output folder; if that run is no longer going, "
                                              r"remove .*\.in-use\.json"):
            with claimed(tmp_path / "out", "a fit"):
                pass
        assert json.loads((tmp_path / "out" / CLAIM_FILE).read_text())["pid"] == other.pid  # left as it was
    finally:
        other.kill()
        other.wait()


def test_a_killed_run_s_claim_is_taken_over_and_removed_at_the_end(tmp_path):
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    _claim_of(tmp_path / "out", gone.pid)
    with claimed(tmp_path / "out", "a fit") as folder:
        assert json.loads((folder / CLAIM_FILE).read_text())["pid"] == os.getpid()
    assert not (tmp_path / "out" / CLAIM_FILE).exists()


def test_a_claim_from_another_host_is_never_taken_over(tmp_path):
    _claim_of(tmp_path / "out", 1, host="another-host.example")
    with pytest.raises(FolderInUse, match="another-host.example"):
        with claimed(tmp_path / "out", "a fit"):
            pass


def test_the_same_process_may_claim_a_folder_it_holds_and_keeps_it_until_the_outer_run_ends(tmp_path):
    with claimed(tmp_path / "out", "a fit"):
        with claimed(tmp_path / "out", "an optimisation"):
            pass
        assert (tmp_path / "out" / CLAIM_FILE).exists()
    assert not (tmp_path / "out" / CLAIM_FILE).exists()


def test_the_claim_is_released_when_the_run_fails(tmp_path):
    with pytest.raises(RuntimeError):
        with claimed(tmp_path / "out", "a fit"):
            raise RuntimeError("the run failed")
    assert not (tmp_path / "out" / CLAIM_FILE).exists()


def test_an_optimisation_into_a_folder_another_process_writes_is_refused_before_it_evaluates(tmp_path):
    from BreastBiomechLib.optimisation import optimise

    class NeverEvaluated:
        objective = "nmi"

        class space:
            dimension = 1

            @staticmethod
            def start():
                return [0.5]

            @staticmethod
            def to_dict():
                return {}

        @staticmethod
        def evaluate(z):
            raise AssertionError("evaluated although the folder is in use")

    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        _claim_of(tmp_path / "fit", other.pid)
        with pytest.raises(FolderInUse):
            optimise(NeverEvaluated(), "cmaes", budget=4, out_dir=tmp_path / "fit")
        assert not (tmp_path / "fit" / "evaluations.jsonl").exists()
    finally:
        other.kill()
        other.wait()


def test_claiming_a_folder_removes_what_dead_writers_left_mid_write(tmp_path):
    """A run killed mid-write leaves its atomic write's temporary file (io/atomic.py); the next
    run that claims the folder removes those of writers on this host that are gone (at any depth),
    and keeps those of live writers and of other hosts (a shared filesystem). CI's kill-and-resume
    trial of a fit once killed a write and found the file after the resume."""
    from BreastBiomechLib.io.atomic import partial_path, write_text_atomically

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    host = socket.gethostname()
    out = tmp_path / "out"
    (out / "round-1").mkdir(parents=True)
    dead = [out / f".partial-{gone.pid}@{host}@evaluations.jsonl",
            out / "round-1" / f".partial-{gone.pid}@{host}@x.nrrd"]
    kept = [partial_path(out / "record.json"), out / f".partial-{gone.pid}@elsewhere.example@y.json"]
    for path in dead + kept:
        path.write_text("half")
    with claimed(out, "a fit"):
        assert [p.exists() for p in dead + kept] == [False, False, True, True]
        write_text_atomically(out / "record.json", "whole")  # this process's own write goes through
    assert (out / "record.json").read_text() == "whole" and not partial_path(out / "record.json").exists()
