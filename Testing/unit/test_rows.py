"""unique_rows gives np.unique(axis=0)'s answer: packed into int64 keys and where it cannot pack."""

import numpy as np
import pytest

from BreastBiomechLib.rows import unique_rows


@pytest.mark.parametrize("high, columns", [(50, 3), (2**20, 3), (2**22, 3), (7, 2), (2**40, 2)])
def test_unique_rows_is_numpy_unique_by_rows(high, columns):
    rng = np.random.default_rng(high + columns)
    rows = rng.integers(0, high, (400, columns))
    rows = np.concatenate([rows, rows[rng.integers(0, len(rows), 200)]])  # repeats to find
    expected = np.unique(rows, axis=0, return_index=True, return_inverse=True, return_counts=True)
    got = unique_rows(rows, return_index=True, return_inverse=True, return_counts=True)
    for e, g in zip(expected, got):
        np.testing.assert_array_equal(g, e.ravel() if e.ndim == 2 and e.shape[1] == 1 else e)
    np.testing.assert_array_equal(unique_rows(rows), expected[0])
    _, counts = unique_rows(rows, return_counts=True)
    np.testing.assert_array_equal(counts, expected[3])


def test_negative_ids_and_no_rows_fall_back_to_numpy():
    rows = np.array([[-1, 2], [3, 4], [-1, 2]])
    np.testing.assert_array_equal(unique_rows(rows), np.unique(rows, axis=0))
    assert unique_rows(np.zeros((0, 3), np.int64)).shape == (0, 3)
