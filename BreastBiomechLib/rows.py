"""Rows of ids (faces, edges, elements) made unique and counted fast.

NumPy's ``np.unique(..., axis=0)`` sorts rows as structured items, which on the million faces of a
fine mesh takes seconds; packing each row's ids into one int64 and sorting those gives the same
answer some twenty times faster. Meshing calls it for every boundary-face search of its repair
rounds."""

from __future__ import annotations

import numpy as np


def unique_rows(rows: np.ndarray, return_index: bool = False, return_inverse: bool = False,
                return_counts: bool = False):
    """``np.unique(rows, axis=0, ...)`` of rows (K, c) of non-negative ids, the same results in
    the same (lexicographic) order, some twenty times faster where a row's ids pack into one
    int64 (c x bits <= 63: up to 2 million nodes for faces), since NumPy sorts rows as
    structured items; the inverse is flat (K,)."""
    rows = np.asarray(rows)
    bits = max(int(rows.max(initial=0)).bit_length(), 1)
    if rows.ndim != 2 or len(rows) == 0 or rows.min() < 0 or bits * rows.shape[1] > 63:
        result = np.unique(rows, axis=0, return_index=True, return_inverse=return_inverse,
                           return_counts=return_counts)
        unique, index, rest = result[0], result[1], list(result[2:])
    else:
        keys = np.zeros(len(rows), np.int64)
        for column in rows.T.astype(np.int64):
            keys = (keys << bits) | column
        _, index, *rest = np.unique(keys, return_index=True, return_inverse=return_inverse,
                                    return_counts=return_counts)
        unique = rows[index]
    if return_inverse:
        rest[0] = rest[0].ravel()
    out = [unique] + ([index] if return_index else []) + rest
    return out[0] if len(out) == 1 else tuple(out)
