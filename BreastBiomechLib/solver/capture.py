"""CUDA graph capture that Python's garbage collector cannot break.

A solve's objects hold their CUDA graphs and device arrays in reference cycles (a batch run and
the stable-step monitor that calls back into it), so they are freed by the cyclic garbage
collector, at whatever allocation triggers it, also while a later solve in the same process is
capturing a graph. Destroying a graph or unloading a module while a stream captures is not
permitted by CUDA: the capture is invalidated and fails with error 901 ("operation failed due to
a previous error during capture", warp issue 992). The varied discrepancy suite lost 2 of 30
cases to it, each in a capture of a relaxation's sample. :func:`graph_capture` pauses automatic
collection for the capture's length (a few milliseconds); the garbage is collected afterwards.
"""

from __future__ import annotations

import contextlib
import gc

import warp as wp


@contextlib.contextmanager
def graph_capture(device=None):
    """``wp.ScopedCapture(device)`` (yielding it; its ``graph`` once the block ends) with the
    automatic garbage collection paused, and restored as it was, for the capture's length."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        with wp.ScopedCapture(device) as capture:
            yield capture
    finally:
        if enabled:
            gc.enable()
