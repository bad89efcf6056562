"""Task functions for the cohort tests (module level, so that Dask workers import them by name)."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path


def square(x: int, out: str, device=None, progress=None) -> dict:
    """Write x² to ``out/<x>.json`` (atomically) after three progress lines; x = 3 raises."""
    from BreastBiomechLib.cohort import write_json_atomically

    for step in range(3):
        if progress("step %d" % step) is False:
            return {"x": x, "stopped": True}
        time.sleep(0.3)
    if x == 3:
        raise ValueError("three is refused")
    write_json_atomically(Path(out) / f"{x}.json", {"x": x, "square": x * x})
    return {"x": x, "square": x * x, "device": device}


def dies_once(out: str, device=None, progress=None) -> dict:
    """Kill its own worker process on its first attempt (a worker lost mid-task); then succeed."""
    marker = Path(out) / "died-once"
    if not marker.exists():
        marker.write_text(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)
    return {"pid": os.getpid(), "first": int(marker.read_text())}


def total(out: str, device=None, progress=None) -> dict:
    """Sum the squares written by :func:`square` (a task that needs them)."""
    return {"total": sum(json.loads(p.read_text())["square"] for p in sorted(Path(out).glob("[0-9]*.json")))}


def pause(seconds: float, device=None, progress=None) -> dict:
    """Take ``seconds`` (a mesh or a fit of a given length)."""
    time.sleep(seconds)
    return {"seconds": seconds}


def environment(name: str, device=None, progress=None) -> dict:
    """The worker's value of the environment variable ``name`` (None: not set)."""
    return {"value": os.environ.get(name)}


def capture_fails_once(out: str, device=None, progress=None) -> dict:
    """Fail its first try as a broken CUDA graph capture does (warp's words), then succeed."""
    marker = Path(out) / "capture-failed-once"
    if not marker.exists():
        marker.write_text(str(os.getpid()))
        raise RuntimeError("Error launching kernel: energies on device cuda:0: Warp CUDA error 901: operation failed "
                           "due to a previous error during capture")
    return {"pid": os.getpid()}


def capture_always_fails(device=None, progress=None) -> dict:
    """Fail every try as a broken CUDA graph capture does."""
    raise RuntimeError("Warp CUDA error 900: operation not permitted when stream is capturing")


def dask_setting(key: str, device=None, progress=None) -> dict:
    """The worker's value of the Dask configuration ``key`` (dotted)."""
    import dask

    return {"value": dask.config.get(key)}
