"""What the command groups share: choices, argparse types, the progress line on standard error."""

from __future__ import annotations

import argparse
import shutil
import sys


MODEL_CHOICES = ("iso-homo", "iso-hetero", "aniso-homo", "aniso-hetero")  # optimisation.space.MODELS
OBJECTIVE_CHOICES = ("nmi", "landmarks", "surface", "nmi+landmarks", "nmi+surface")  # optimisation.forward.OBJECTIVES


_line = {"open": False}  # a progress line waits for its newline on standard error


def progress_line(quiet: bool):
    """A progress callback that redraws one line on standard error (silent when ``quiet``)."""
    def report(fraction, message):
        if not quiet:
            print(f"\r  {fraction:4.0%} {message:40s}", end="", file=sys.stderr, flush=True)
            _line["open"] = True
    return report


def end_progress() -> None:
    if _line["open"]:
        print(file=sys.stderr)
        _line["open"] = False


def device_argument(text: str) -> str:
    """argparse type of ``--device``: cpu, cuda or cuda:K (warp's device names), so that a typo
    is refused before anything runs."""
    if text in ("cpu", "cuda") or (text.startswith("cuda:") and text[5:].isdigit()):
        return text
    raise argparse.ArgumentTypeError(f"takes cpu, cuda or cuda:K (a GPU's number), not {text!r}")


def _number(text: str, kind, test, wanted: str):
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be {wanted}, not {text!r}") from None
    if not (value == value and abs(value) < float("inf") and test(value)):  # NaN and infinities fail
        raise argparse.ArgumentTypeError(f"must be {wanted}, not {text}")
    return value


def finite(text: str) -> float:
    """An argparse type: a finite number (no NaN or infinity)."""
    return _number(text, float, lambda v: True, "a finite number")


def positive(text: str) -> float:
    """An argparse type: a finite number > 0."""
    return _number(text, float, lambda v: v > 0, "a finite number > 0")


def fraction(text: str) -> float:
    """An argparse type: a number strictly between 0 and 1."""
    return _number(text, float, lambda v: 0 < v < 1, "a number between 0 and 1")


def weight(text: str) -> float:
    """An argparse type: a number >= 0 and below 1."""
    return _number(text, float, lambda v: 0 <= v < 1, "a number >= 0 and below 1")


def positive_int(text: str) -> int:
    """An argparse type: a whole number >= 1."""
    return _number(text, int, lambda v: v >= 1, "a whole number >= 1")


def non_negative_int(text: str) -> int:
    """An argparse type: a whole number >= 0."""
    return _number(text, int, lambda v: v >= 0, "a whole number >= 0")


def non_negative(text: str) -> float:
    """An argparse type: a finite number >= 0."""
    return _number(text, float, lambda v: v >= 0, "a finite number >= 0")


def add_cluster_options(p: argparse.ArgumentParser) -> None:
    """``--scheduler`` and ``--workers``: where a cohort command's tasks run
    (:func:`BreastBiomechLib.cohort.place`)."""
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="an existing Dask cluster's scheduler (tcp://HOST:PORT; default: the environment's "
                        "BREASTBIOMECH_SCHEDULER, else a local cluster made for the run)")
    p.add_argument("--workers", type=non_negative_int, metavar="N",
                   help="local cluster's worker processes (default: one per GPU, or one per core without a GPU; "
                        "several may share a GPU; 0: run every task in this process)")


def cohort_progress(quiet: bool):
    """A progress callback for :func:`BreastBiomechLib.cohort.run_tasks`: says once where the tasks
    run (and the dashboard's address), then redraws a bar over the tasks on standard error."""
    said = {"where": False, "width": 0}

    def report(state):
        if quiet:
            return
        if not said["where"]:
            said["where"] = True
            print(f"  tasks run on {state.where}" + (f"; dashboard {state.dashboard}" if state.dashboard else ""),
                  file=sys.stderr, flush=True)
        text = state.line()[: shutil.get_terminal_size((120, 20)).columns - 3]
        if text == said.get("text"):
            return
        said["text"] = text
        print("\r  " + text.ljust(said["width"]), end="", file=sys.stderr, flush=True)  # blank what was longer
        said["width"] = len(text)
        _line["open"] = True
    return report


def report_failures(failed, log_path) -> None:
    """One line per failed task on standard error, and where their tracebacks are."""
    end_progress()
    for outcome in failed:
        print(f"  FAILED {outcome.label}: {outcome.error}", file=sys.stderr)
    if failed:
        print(f"  {len(failed)} task{'s' * (len(failed) != 1)} failed; tracebacks in {log_path}; the others finished, "
              "and a rerun tries the failed ones again", file=sys.stderr)
