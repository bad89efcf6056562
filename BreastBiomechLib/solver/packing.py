"""Moving a batch's per-model arrays to a batch of other models: packing a solve down to the models
still moving, and putting a finished model's values back in the batch's first numbering.

Every per-model array of a solve keeps its models innermost (see :mod:`kernels`): entry i of model
b of an array of B models at ``(o * B + b) * I + i`` for an outer index o (a node, an element, a
slot, a table row or a force plane) and I entries per model and outer index (one mostly; four
flags, P plate poses, K Prony terms). A model left alone in a batch of sixteen still reads its
nodes one per 32-byte memory sector, and the batch's samples sum over all sixteen: it stepped in
32 us an iteration against 16 us solved alone (54k tets, H200, docs/benchmarks.md). Packed into a
batch of its own size it steps as if alone.

The copies work on the arrays' memory as 32-bit words, whatever their dtype (float32, int32,
float64, vectors, matrices, structs of those), on the device, in the stream's order: no host
synchronisation, so work already enqueued on the old arrays runs first.
"""

from __future__ import annotations

import numpy as np
import warp as wp

WORD = 4  # bytes of the copies' unit


@wp.kernel
def copy_models(src: wp.array(dtype=wp.int32), src_models: int, src_of: wp.array(dtype=int),
                dst: wp.array(dtype=wp.int32), dst_models: int, dst_of: wp.array(dtype=int), words: int):
    """Model ``src_of[j]`` of ``src`` (a batch of ``src_models``) into model ``dst_of[j]`` of
    ``dst`` (of ``dst_models``), ``words`` 32-bit words per model and outer index; one thread per
    word copied (outer index, entry j of the lists, word)."""
    tid = wp.tid()
    count = src_of.shape[0]
    w = tid % words
    rest = tid // words
    j = rest % count
    o = rest // count
    dst[(o * dst_models + dst_of[j]) * words + w] = src[(o * src_models + src_of[j]) * words + w]


def _words(array: wp.array) -> wp.array:
    """``array``'s memory as 32-bit words (a view: ``array`` must outlive it)."""
    nbytes = array.size * wp.types.type_size_in_bytes(array.dtype)
    if not array.is_contiguous or nbytes % WORD:
        raise ValueError("only contiguous arrays of 32-bit words can be moved between batches")
    return wp.array(ptr=array.ptr, dtype=wp.int32, shape=(nbytes // WORD,), device=array.device, copy=False)


def holds_models(array: wp.array, n_models: int, per_model: int = 1) -> bool:
    """Whether ``array`` holds ``per_model`` entries per outer index for each of ``n_models``
    models; a solve's one-entry stand-ins for arrays a batch does not need (no plates,
    constraints or Prony terms) do not."""
    span = n_models * per_model
    return span > 0 and array.size >= span and array.shape[-1] % span == 0


class Selection:
    """The models ``models`` (in that order) of a batch of ``n_models`` on ``device``, and
    optionally the ``positions`` they take in another batch: their indices copied to the device
    once for every array a packing moves (a copy from host memory waits for the device's queue)."""

    def __init__(self, models: np.ndarray, n_models: int, device, positions: np.ndarray | None = None) -> None:
        self.models = np.asarray(models, np.int64)
        self.n_models = int(n_models)
        if positions is not None and len(positions) != len(self.models):
            raise ValueError("a selection needs one position for each model")
        self._models = wp.array(self.models.astype(np.int32), dtype=int, device=device)
        taken = np.arange(len(self.models)) if positions is None else np.asarray(positions)
        self._positions = wp.array(taken.astype(np.int32), dtype=int, device=device)

    def __len__(self) -> int:
        return len(self.models)

    def take(self, array: wp.array, per_model: int = 1) -> wp.array:
        """A new array of the selected models of ``array`` (a batch of :attr:`n_models` with
        ``per_model`` entries per model and outer index), in their order; its last dimension
        shrinks in proportion. A one-entry stand-in (see :func:`holds_models`) is returned as it is."""
        if not holds_models(array, self.n_models, per_model):
            return array
        shape = array.shape[:-1] + (array.shape[-1] // self.n_models * len(self),)
        out = wp.empty(shape, dtype=array.dtype, device=array.device)
        self._copy(array, out, len(self), per_model)
        return out

    def put(self, array: wp.array, into: wp.array, into_models: int, per_model: int = 1) -> None:
        """The selected models of ``array`` into their ``positions`` of ``into`` (an array of the
        same dtype and layout for a batch of ``into_models``); device work."""
        if holds_models(array, self.n_models, per_model):
            self._copy(array, into, into_models, per_model)

    def _copy(self, src: wp.array, dst: wp.array, dst_models: int, per_model: int) -> None:
        words = per_model * (wp.types.type_size_in_bytes(src.dtype) // WORD)
        outer = src.size // (self.n_models * per_model)
        if len(self) and outer:
            wp.launch(copy_models, outer * len(self) * words,
                      [_words(src), self.n_models, self._models, _words(dst), dst_models, self._positions, words],
                      device=src.device)
