"""Timing kernels as the solver runs them: launched from a captured CUDA graph (issue 25).

Shared by this folder's scripts (``solver_profile.py``, ``node_update_floor.py``). Wall clock over
synchronised replays after a warm-up; nothing is asserted.
"""

from __future__ import annotations

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
