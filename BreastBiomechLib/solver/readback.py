"""Small device arrays that a solve reads back at every sample, without a wait per array.

warp's ``array.numpy()`` of a CUDA array allocates a host array, copies into it and waits for the
device, each time, in Python; a relaxation's sample read nine arrays of a few numbers each that way
while the GPU stood idle (the host's time between a sample and the next steps, most of it the
relaxation's decisions, is 10-15 % of a lone 160k-tet solve on an H200, docs/benchmarks.md). A
:class:`HostCopy` keeps a pinned host array for one device array: :meth:`HostCopy.refresh` enqueues
the copy (device work, so it can be captured in the sample's CUDA graph and every replay refreshes
it), :meth:`HostCopy.read` waits for the device's stream - the first read of a sample waits for its
work, the others find the stream idle - and returns the values. On the CPU device the host copy is
the array itself.
"""

from __future__ import annotations

import numpy as np
import warp as wp


class HostCopy:
    """The host's copy of the device array ``array`` (same shape and dtype), as of the last
    :meth:`refresh` that the device has carried out."""

    def __init__(self, array: wp.array) -> None:
        self._array = array
        self._cuda = array.device.is_cuda
        self._host = wp.empty(array.shape, dtype=array.dtype, device="cpu", pinned=True) if self._cuda else array
        self._view = self._host.numpy()  # host memory does not move: one view for every read (numpy() costs 15 us)

    def refresh(self) -> None:
        """Enqueue the copy on the device's current stream (nothing to do on the CPU)."""
        if self._cuda:
            wp.copy(self._host, self._array)

    def read(self) -> np.ndarray:
        """The values (a NumPy array of their own, in the array's shape and dtype) once the device's
        stream has carried out everything enqueued on it, the last refresh included."""
        if self._cuda:
            wp.synchronize_stream(self._array.device.stream)
        return np.array(self._view)
