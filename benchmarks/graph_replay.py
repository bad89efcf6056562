"""Timing kernels as the solver runs them: its own launches recorded, and replayed from a captured
CUDA graph (issue 25).

Shared by this folder's scripts (``solver_profile.py``, ``node_update_floor.py``,
``node_kernel_parts.py``). Wall clock over synchronised replays after a warm-up; nothing is
asserted.
"""

from __future__ import annotations

import contextlib
import time

import warp as wp


def replayed(launches: list, repeats: int = 20, replays: int = 100) -> float:
    """µs per repeat of ``launches`` ((kernel, dim, inputs, block_dim) in order, on the current
    CUDA device), replayed as a CUDA graph of ``repeats`` repeats, after a warm-up; the best of
    three."""
    with wp.ScopedCapture() as capture:
        for _ in range(repeats):
            for kernel, dim, inputs, block_dim in launches:
                wp.launch(kernel, dim, inputs, block_dim=block_dim)
    best = float("inf")
    for _ in range(3):
        for _ in range(5):
            wp.capture_launch(capture.graph)
        wp.synchronize()
        started = time.perf_counter()
        for _ in range(replays):
            wp.capture_launch(capture.graph)
        wp.synchronize()
        best = min(best, 1e6 * (time.perf_counter() - started) / (repeats * replays))
    return best


@contextlib.contextmanager
def recorded_launches():
    """Within the block, every ``wp.launch`` (the solver's included) is made as usual and
    recorded, in order, as (kernel, dim, inputs, block_dim) in the list the block gets: what
    :func:`replayed` takes. A solve that replays CUDA graphs launches each graph's kernels once,
    when it captures it."""
    recorded = []
    launch = wp.launch

    def recording(kernel, dim, inputs=None, *args, **kwargs):
        recorded.append((kernel, dim, list(inputs or []), kwargs.get("block_dim", 256)))
        return launch(kernel, dim, inputs, *args, **kwargs)

    wp.launch = recording
    try:
        yield recorded
    finally:
        wp.launch = launch


def argument(record: tuple, name: str):
    """The value a recorded launch (kernel, dim, inputs, block_dim) passed for argument ``name``."""
    kernel, _, inputs, _ = record
    return inputs[[a.label for a in kernel.adj.args].index(name)]
