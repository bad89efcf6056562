"""Warp kernels of the similarity measures: a joint intensity histogram and the moments of a
pair of images, over the voxels of a mask. Each thread takes a run of ``chunk`` voxels and
accumulates locally before its atomic adds, so contention stays low on the GPU."""

from __future__ import annotations

import warp as wp


@wp.kernel
def joint_histogram(a: wp.array(dtype=float), b: wp.array(dtype=float), mask: wp.array(dtype=wp.int32),
                    a_low: float, a_scale: float, b_low: float, b_scale: float, bins: int, chunk: int,
                    histogram: wp.array(dtype=float)):
    """histogram[i * bins + j] counts the masked voxels with a in bin i and b in bin j; bin =
    floor((value - low) * scale), values outside the range counted in the edge bins."""
    t = wp.tid()
    start = t * chunk
    stop = wp.min(start + chunk, a.shape[0])
    for v in range(start, stop):
        if mask[v] != 0:
            i = wp.clamp(int(wp.floor((a[v] - a_low) * a_scale)), 0, bins - 1)
            j = wp.clamp(int(wp.floor((b[v] - b_low) * b_scale)), 0, bins - 1)
            wp.atomic_add(histogram, i * bins + j, 1.0)


@wp.kernel
def pair_moments(a: wp.array(dtype=float), b: wp.array(dtype=float), mask: wp.array(dtype=wp.int32),
                 a_shift: float, b_shift: float, chunk: int, sums: wp.array(dtype=wp.float64)):
    """sums += (n, sum a', sum b', sum a'^2, sum b'^2, sum a'b') over the masked voxels, with
    a' = a - a_shift and b' = b - b_shift (shifts near the means keep the float64 sums exact
    enough for the variances)."""
    t = wp.tid()
    start = t * chunk
    stop = wp.min(start + chunk, a.shape[0])
    n = wp.float64(0.0)
    sa = wp.float64(0.0)
    sb = wp.float64(0.0)
    saa = wp.float64(0.0)
    sbb = wp.float64(0.0)
    sab = wp.float64(0.0)
    for v in range(start, stop):
        if mask[v] != 0:
            x = wp.float64(a[v] - a_shift)
            y = wp.float64(b[v] - b_shift)
            n += wp.float64(1.0)
            sa += x
            sb += y
            saa += x * x
            sbb += y * y
            sab += x * y
    wp.atomic_add(sums, 0, n)
    wp.atomic_add(sums, 1, sa)
    wp.atomic_add(sums, 2, sb)
    wp.atomic_add(sums, 3, saa)
    wp.atomic_add(sums, 4, sbb)
    wp.atomic_add(sums, 5, sab)
