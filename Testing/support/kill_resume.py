"""Kill-and-resume trials (Testing/test_kill_resume*.py): run a command of the CLI to its end, or
kill it with SIGKILL after a while, at kill points drawn at random.

``BREASTBIOMECH_KILL_TRIALS`` sets the kill points per command (default 2, CI's; the long run of
docs/reliability.md uses 20) and ``BREASTBIOMECH_KILL_SEED`` their random draw.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time

TRIALS = int(os.environ.get("BREASTBIOMECH_KILL_TRIALS", "2"))
SEED = int(os.environ.get("BREASTBIOMECH_KILL_SEED", "0"))
CLI = [sys.executable, "-c", "import sys; from BreastBiomechLib.cli import main; sys.exit(main())"]


def run(argv: list[str]) -> float:
    """Run the command to its end (it must succeed); its wall seconds."""
    started = time.perf_counter()
    done = subprocess.run(CLI + argv, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    return time.perf_counter() - started


def kill_after(argv: list[str], seconds: float) -> bool:
    """Start the command and SIGKILL it after ``seconds``; whether it was still running."""
    process = subprocess.Popen(CLI + argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               start_new_session=True)
    try:
        process.wait(timeout=seconds)
        return False
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
        return True


def kill_points(reference_seconds: float, salt: int) -> list[float]:
    """TRIALS delays (s), drawn uniformly over the middle 80 % of the reference run's wall time."""
    draw = random.Random(SEED * 1000 + salt)
    return sorted(draw.uniform(0.1, 0.9) * reference_seconds for _ in range(TRIALS))


def interrupt(argv_in, delay: float, tmp_path, name: str):
    """Kill the command writing to a fresh folder after ``delay`` seconds; where it ended first (a run
    after the reference is faster: warp's kernels are compiled and cached by then), try again in a
    fresh folder at half the delay, so that every trial interrupts something. The folder and the
    delay at which it was killed."""
    for attempt in range(6):
        out = tmp_path / f"{name}-{attempt}"
        if kill_after(argv_in(out), delay):
            return out, delay
        delay /= 2
    raise AssertionError(f"{name}: the command ended before every kill down to {delay:.2f} s")


def assert_resumes_to(reference: dict, seconds: float, command, outputs, tmp_path, salt: int) -> None:
    """Run the kill-and-resume trials: for each kill point, interrupt ``command(out)``, run
    ``command(out, resume=True)`` to its end, and require ``outputs(out)`` to equal ``reference``
    key by key (``reference`` is ``outputs`` of an uninterrupted run of ``seconds`` s) with no
    temporary file left behind."""
    for k, delay in enumerate(kill_points(seconds, salt)):
        out, delay = interrupt(command, delay, tmp_path, f"killed{k}")
        run(command(out, resume=True))
        resumed = outputs(out)
        for key, value in reference.items():
            assert resumed[key] == value, f"kill at {delay:.1f} s of {seconds:.1f} s: {key} differs after the resume"
        assert_no_partial_files(out)


def kill_at(argv: list[str], message: str) -> list[str] | None:
    """Start the command (with its progress on standard error) and SIGKILL it as soon as a line of
    its progress holds ``message``; the lines it said up to then (None: it ended without saying it)."""
    process = subprocess.Popen(CLI + argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                               start_new_session=True)
    heard = []
    try:
        for line in process.stderr:
            heard.append(line)
            if message in line:
                os.killpg(process.pid, signal.SIGKILL)
                return heard
        return None
    finally:
        process.stderr.close()
        process.wait()


def assert_resumes_through_checkpoints(reference: dict, command, outputs, tmp_path, messages: list[str],
                                       resumed_says: list[str] = ()) -> None:
    """One run killed at each progress message of ``messages`` in turn: ``command(out,
    progress=True)`` killed as soon as it reports the first, then ``command(out, resume=True,
    progress=True)`` killed at each next one (a resumed run killed again; the k-th of them must
    have said ``resumed_says[k - 1]`` where given: how it took up what the killed run left), then
    resumed to its end; ``outputs(out)`` must equal ``reference`` key by key, with no temporary
    file left behind. One run through every checkpoint, not a fresh run per checkpoint: the
    solves before a later checkpoint are not made again from the start for it."""
    out = tmp_path / "killed"
    for k, message in enumerate(messages):
        heard = kill_at(command(out, resume=k > 0, progress=True), message)
        assert heard is not None, f"the {'resumed ' if k else ''}command never reported {message!r}"
        if 0 < k <= len(resumed_says):
            assert any(resumed_says[k - 1] in line for line in heard), \
                f"the resumed command did not say {resumed_says[k - 1]!r}: {''.join(heard)[-1500:]}"
    run(command(out, resume=True))
    resumed = outputs(out)
    for key, value in reference.items():
        assert resumed[key] == value, f"killed at {messages}: {key} differs after the resume"
    assert_no_partial_files(out)


def assert_no_partial_files(out) -> None:
    assert not [p for p in out.rglob("*") if p.name.startswith(".partial-")], "a temporary file was left behind"
