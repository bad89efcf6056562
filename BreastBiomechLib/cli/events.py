"""Machine-readable progress of a long command (``--progress json``), for a caller in another
process: the Slicer panels run ``simulate``, ``optimise`` and ``diagnose`` out of Slicer's
process and read these lines (BreastBiomech/BreastBiomechCommon/worker.py).

While a command runs with ``--progress json`` its standard output carries only events, one JSON
object per line, flushed as written; the command's report for people goes to standard error.

- ``{"event": "start", "command": "simulate", "pid": 1234, "seconds": 0.0}`` first;
- ``{"event": "progress", "message": "...", "fraction": 0.42, "seconds": 12.3}`` as the work
  advances (``fraction`` of the whole in [0, 1], or null where the command cannot say);
- ``{"event": "done", "exit": 0, "seconds": 80.1, ...}`` last when the command returns, with
  what it wrote (``outputs``: {name: path}) where it says;
- ``{"event": "error", "exit": 2, "message": "...", "seconds": ...}`` last when it fails on a
  bad input or output (the same sentence the command prints), ``"exit": 130`` when cancelled.

A process killed from outside (the panels' Cancel) writes no last event: its caller knows. The
commands write their files atomically, so what a killed command leaves is whole, and the same
command given ``--resume`` goes on from it (``optimise``, ``diagnose``). ``seconds`` counts from
the command's start (wall clock).
"""

from __future__ import annotations

import json
import math
import os
import sys
import time


PROGRESS_CHOICES = ("bar", "json", "none")  # a command's --progress


class EventStream:
    """Writes the events of one command run to ``stream`` (the process's real standard output)."""

    def __init__(self, stream, command: str):
        self.stream = stream
        self.command = command
        self.started = time.perf_counter()
        self.outputs: dict[str, str] = {}
        self._write({"event": "start", "command": command, "pid": os.getpid()})

    def _write(self, event: dict) -> None:
        event["seconds"] = round(time.perf_counter() - self.started, 3)
        self.stream.write(json.dumps(event) + "\n")
        self.stream.flush()

    def progress(self, message: str, fraction: float | None = None) -> None:
        """One step of the work: ``message`` for a person, ``fraction`` of the whole (None: unknown)."""
        if fraction is not None:
            fraction = float(fraction)
            fraction = min(max(fraction, 0.0), 1.0) if math.isfinite(fraction) else None
        self._write({"event": "progress", "message": str(message), "fraction": fraction})

    def output(self, name: str, path) -> None:
        """Record a file or folder the command wrote, for the last event."""
        self.outputs[name] = str(path)

    def done(self, code: int) -> None:
        self._write({"event": "done", "exit": int(code), "outputs": self.outputs})

    def error(self, code: int, message: str) -> None:
        self._write({"event": "error", "exit": int(code), "message": message})


class _Silent:
    """The stand-in where a command runs without ``--progress json``: every call does nothing."""

    def progress(self, message: str, fraction: float | None = None) -> None:
        pass

    def output(self, name: str, path) -> None:
        pass


SILENT = _Silent()


def events_of(args):
    """The command's :class:`EventStream` (``args.events``, set by ``main`` for ``--progress
    json``) or a silent stand-in."""
    return getattr(args, "events", None) or SILENT


def wants_bar(args) -> bool:
    """Whether the command draws its progress for a person on standard error."""
    return getattr(args, "progress", "bar") == "bar" and not getattr(args, "quiet", False)


def add_progress_option(parser) -> None:
    """``--progress bar|json|none`` and ``--quiet`` (the same as ``--progress none``) on ``parser``."""
    parser.add_argument("--progress", choices=PROGRESS_CHOICES, default="bar",
                        help="bar: progress for a person on standard error (default); json: one JSON event per "
                             "line on standard output, the report on standard error (for a program: "
                             "BreastBiomechLib/cli/events.py); none: no progress")
    parser.add_argument("--quiet", action="store_true", help="no progress (--progress none)")


def open_events(args):
    """For ``--progress json``: the event stream on the real standard output, which from now on
    takes only events (``sys.stdout`` is pointed at standard error for everything else). None
    otherwise. Returns (events, restore) where ``restore()`` puts standard output back."""
    if getattr(args, "progress", None) != "json":
        return None, lambda: None
    real = sys.stdout
    events = EventStream(real, args.command)
    sys.stdout = sys.stderr

    def restore() -> None:
        sys.stdout = real
    return events, restore

