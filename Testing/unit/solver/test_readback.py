"""The host's copies of what a solve reads at each sample (solver/readback.py): a read holds the
values of the last refresh the device has carried out, and stays what it was when the array
changes after it; on CUDA the refresh works from inside a captured graph, every replay copying
anew."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from BreastBiomechLib.solver.readback import HostCopy


@wp.kernel
def _add_one(values: wp.array(dtype=float)):
    i = wp.tid()
    values[i] = values[i] + 1.0


def test_a_read_is_the_values_of_its_time_on_the_cpu():
    wp.init()
    values = wp.array(np.array([1.0, 2.0, 3.0], np.float32), dtype=float, device="cpu")
    copy = HostCopy(values)
    copy.refresh()
    first = copy.read()
    wp.launch(_add_one, 3, [values], device="cpu")
    copy.refresh()
    np.testing.assert_array_equal(first, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(copy.read(), [2.0, 3.0, 4.0])


def test_a_read_holds_the_last_refresh_not_later_changes_on_the_cpu():
    """A relaxation's next steps run between a sample's refresh and its read: the read must be
    the sample's values (on the CPU device the steps change the array before the read)."""
    wp.init()
    values = wp.array(np.array([1.0, 2.0], np.float32), dtype=float, device="cpu")
    copy = HostCopy(values)
    copy.refresh()
    wp.launch(_add_one, 2, [values], device="cpu")
    np.testing.assert_array_equal(copy.read(), [1.0, 2.0])


def test_a_vector_array_reads_back_in_its_shape():
    wp.init()
    forces = wp.array(np.arange(6, dtype=np.float32).reshape(2, 3), dtype=wp.vec3, device="cpu")
    copy = HostCopy(forces)
    copy.refresh()
    read = copy.read()
    assert read.shape == (2, 3)
    np.testing.assert_array_equal(read, np.arange(6).reshape(2, 3))


def test_a_copy_follows_a_smaller_array_of_its_dtype_and_refuses_others():
    """A packed solve's copies follow the packed arrays in the host memory they have: a read is
    the new array's values in its shape, never the rest of the old array's."""
    wp.init()
    copy = HostCopy(wp.array(np.arange(8, dtype=np.float32).reshape(4, 2), dtype=wp.vec2, device="cpu"))
    copy.refresh()
    smaller = wp.array(np.array([[10.0, 11.0]], np.float32), dtype=wp.vec2, device="cpu")
    copy.follow(smaller)
    copy.refresh()
    np.testing.assert_array_equal(copy.read(), [[10.0, 11.0]])
    with pytest.raises(ValueError, match="no larger"):
        copy.follow(wp.zeros(5, dtype=wp.vec2, device="cpu"))
    with pytest.raises(ValueError, match="dtype"):
        copy.follow(wp.zeros(1, dtype=float, device="cpu"))


@pytest.mark.gpu
def test_a_refresh_captured_in_a_graph_copies_at_every_replay(cuda):
    values = wp.zeros(4, dtype=float)
    copy = HostCopy(values)
    with wp.ScopedCapture() as capture:
        wp.launch(_add_one, 4, [values])
        copy.refresh()
    for replays in (1, 2, 3):
        wp.capture_launch(capture.graph)
        np.testing.assert_array_equal(copy.read(), np.full(4, float(replays)))
