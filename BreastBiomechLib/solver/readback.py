"""Small device arrays that a solve reads back at every sample, without a wait per array.

warp's ``array.numpy()`` of a CUDA array allocates a host array, copies into it and waits for the
device, each time, in Python; a relaxation's sample read nine arrays of a few numbers each that way
while the GPU stood idle. A :class:`HostCopy` keeps a pinned host array for one device array:
:meth:`HostCopy.refresh` enqueues the copy (device work, so it can be captured in the sample's CUDA
graph and every replay refreshes it), :meth:`HostCopy.read` waits for the device - for its stream,
or only up to an event recorded after the refresh, so that work enqueued after it (the next steps
of a relaxation, which run while the host reads) is not waited for - and returns the values. On the
CPU device too the read is the values as of the refresh, whatever ran since.
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
        self._host = wp.empty(array.size, dtype=array.dtype, device="cpu", pinned=self._cuda)
        self._view = self._host.numpy()  # host memory does not move: one view for every read (numpy() costs 15 us)

    def follow(self, array: wp.array) -> None:
        """Copy ``array`` from now on (of the same dtype and no larger than the first array), in
        the same host memory: a pinned allocation costs more than the copies of a solve's samples."""
        if array.dtype != self._array.dtype or array.size > self._host.size:
            raise ValueError("a host copy follows arrays of its dtype no larger than its first")
        self._array = array

    def refresh(self) -> None:
        """Enqueue the copy on the device's current stream (made at once on the CPU device)."""
        wp.copy(self._host, self._array, count=self._array.size)

    def read(self, after: wp.Event | None = None) -> np.ndarray:
        """The values (a NumPy array of their own, in the array's shape and dtype) once the device
        has carried out its work up to the event ``after`` (recorded after the refresh to read), or
        without it everything enqueued on its stream."""
        if self._cuda:
            if after is None:
                wp.synchronize_stream(self._array.device.stream)
            else:
                wp.synchronize_event(after)
        values = self._view[:self._array.size]  # (entries, then a vector's or matrix's shape)
        return np.array(values).reshape(self._array.shape + values.shape[1:])
