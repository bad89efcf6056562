"""Graph capture with the garbage collector paused (solver/capture.py): no automatic collection
runs inside a capture, the collector is restored after it (also when the block raises), and on
CUDA an earlier solve's graph left in a reference cycle cannot be destroyed inside a capture."""

from __future__ import annotations

import gc

import numpy as np
import pytest
import warp as wp

from BreastBiomechLib.solver.capture import graph_capture


@wp.kernel
def _add_one(values: wp.array(dtype=float)):
    i = wp.tid()
    values[i] = values[i] + 1.0


class _Cycle:
    """Holds a graph in a reference cycle, as a finished batch run does."""

    def __init__(self, graph):
        self.graph, self.me = graph, self


@pytest.mark.parametrize("enabled", [True, False])
def test_the_collector_is_paused_for_the_capture_and_restored_after(enabled):
    wp.init()
    was = gc.isenabled()
    try:
        gc.enable() if enabled else gc.disable()
        values = wp.zeros(3, dtype=float, device="cpu")
        with graph_capture("cpu") as capture:
            assert not gc.isenabled()
            wp.launch(_add_one, 3, [values], device="cpu")
        assert gc.isenabled() == enabled and capture.graph is not None
        with pytest.raises(RuntimeError, match="inside"):
            with graph_capture("cpu"):
                raise RuntimeError("inside")
        assert gc.isenabled() == enabled
    finally:
        gc.enable() if was else gc.disable()


@pytest.mark.gpu
def test_garbage_holding_a_graph_is_not_collected_inside_a_capture(cuda):
    values = wp.zeros(4, dtype=float)
    for _ in range(3):
        with graph_capture() as earlier:
            wp.launch(_add_one, 4, [values])
        _Cycle(earlier.graph)  # garbage that only the cyclic collector frees
        del earlier
        with graph_capture() as capture:
            [[] for _ in range(10 * gc.get_threshold()[0])]  # tracked containers: would trigger a collection
            wp.launch(_add_one, 4, [values])
        wp.capture_launch(capture.graph)
    wp.synchronize()
    np.testing.assert_array_equal(values.numpy(), [3.0] * 4)
    gc.collect()  # the earlier graphs, outside any capture
