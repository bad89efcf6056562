"""What the command groups share: choices, argparse types, the progress line on standard error."""

from __future__ import annotations

import argparse
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


def non_negative(text: str) -> float:
    """An argparse type: a finite number >= 0."""
    value = float(text)
    if not (value >= 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, not {text}")
    return value
