"""Warp kernels of the image warping: locate voxel centres in the deformed mesh, sample an image.

Geometry: points in LPS millimetres; a grid maps its continuous index (i, j, k) to LPS as
``origin + to_lps @ (i, j, k)`` (``to_lps`` = direction @ diag(spacing)) and back with
``to_index``. Voxel arrays are flattened in SimpleITK's (z, y, x) order: (k * ny + j) * nx + i.
"""

from __future__ import annotations

import warp as wp

BARYCENTRIC_TOLERANCE = 1e-5  # a voxel centre on a shared face belongs to both tets (same map)


@wp.kernel
def locate_in_tets(deformed: wp.array(dtype=wp.vec3), reference: wp.array(dtype=wp.vec3),
                   tets: wp.array2d(dtype=int), origin: wp.vec3, to_lps: wp.mat33, to_index: wp.mat33,
                   nx: int, ny: int, nz: int,
                   position: wp.array(dtype=wp.vec3), inside: wp.array(dtype=wp.int32)):
    """One thread per tet: every voxel centre of the output grid inside the deformed tet gets
    its reference position (the same barycentric combination of the reference nodes)."""
    t = wp.tid()
    p0 = deformed[tets[t, 0]]
    p1 = deformed[tets[t, 1]]
    p2 = deformed[tets[t, 2]]
    p3 = deformed[tets[t, 3]]
    c0 = to_index * (p0 - origin)
    c1 = to_index * (p1 - origin)
    c2 = to_index * (p2 - origin)
    c3 = to_index * (p3 - origin)
    lo = wp.min(wp.min(c0, c1), wp.min(c2, c3))
    hi = wp.max(wp.max(c0, c1), wp.max(c2, c3))
    i0 = wp.max(int(wp.ceil(lo[0] - 1.0e-4)), 0)
    j0 = wp.max(int(wp.ceil(lo[1] - 1.0e-4)), 0)
    k0 = wp.max(int(wp.ceil(lo[2] - 1.0e-4)), 0)
    i1 = wp.min(int(wp.floor(hi[0] + 1.0e-4)), nx - 1)
    j1 = wp.min(int(wp.floor(hi[1] + 1.0e-4)), ny - 1)
    k1 = wp.min(int(wp.floor(hi[2] + 1.0e-4)), nz - 1)
    if i0 > i1 or j0 > j1 or k0 > k1:
        return
    e1 = p1 - p0
    e2 = p2 - p0
    e3 = p3 - p0
    edges = wp.mat33(e1[0], e2[0], e3[0], e1[1], e2[1], e3[1], e1[2], e2[2], e3[2])
    det = wp.determinant(edges)
    scale = wp.length(e1) * wp.length(e2) * wp.length(e3)
    if wp.abs(det) <= 1.0e-9 * scale:
        return  # a flat tet covers no voxel centre
    to_barycentric = wp.inverse(edges)
    r0 = reference[tets[t, 0]]
    r1 = reference[tets[t, 1]]
    r2 = reference[tets[t, 2]]
    r3 = reference[tets[t, 3]]
    for k in range(k0, k1 + 1):
        for j in range(j0, j1 + 1):
            for i in range(i0, i1 + 1):
                x = origin + to_lps * wp.vec3(float(i), float(j), float(k))
                b = to_barycentric * (x - p0)
                b0 = 1.0 - b[0] - b[1] - b[2]
                if wp.min(wp.min(b0, b[0]), wp.min(b[1], b[2])) >= -BARYCENTRIC_TOLERANCE:
                    v = (k * ny + j) * nx + i
                    position[v] = r0 * b0 + r1 * b[0] + r2 * b[1] + r3 * b[2]
                    inside[v] = 1


@wp.kernel
def sample_linear(position: wp.array(dtype=wp.vec3), inside: wp.array(dtype=wp.int32),
                  image: wp.array3d(dtype=float), origin: wp.vec3, to_index: wp.mat33, background: float,
                  out: wp.array(dtype=float)):
    """One thread per output voxel: the image (arrays (z, y, x)) at the voxel's reference
    position by trilinear interpolation; ``background`` where the voxel is outside the deformed
    mesh or its reference position is more than half a voxel outside the image (as ITK)."""
    v = wp.tid()
    if inside[v] == 0:
        out[v] = background
        return
    c = to_index * (position[v] - origin)
    nz = image.shape[0]
    ny = image.shape[1]
    nx = image.shape[2]
    if c[0] < -0.5 or c[1] < -0.5 or c[2] < -0.5 or c[0] > float(nx) - 0.5 or c[1] > float(ny) - 0.5 \
            or c[2] > float(nz) - 0.5:
        out[v] = background
        return
    x = wp.clamp(c[0], 0.0, float(nx - 1))
    y = wp.clamp(c[1], 0.0, float(ny - 1))
    z = wp.clamp(c[2], 0.0, float(nz - 1))
    i = wp.min(int(x), nx - 2)
    j = wp.min(int(y), ny - 2)
    k = wp.min(int(z), nz - 2)
    i = wp.max(i, 0)
    j = wp.max(j, 0)
    k = wp.max(k, 0)
    fx = x - float(i)
    fy = y - float(j)
    fz = z - float(k)
    i1 = wp.min(i + 1, nx - 1)
    j1 = wp.min(j + 1, ny - 1)
    k1 = wp.min(k + 1, nz - 1)
    c00 = image[k, j, i] * (1.0 - fx) + image[k, j, i1] * fx
    c01 = image[k, j1, i] * (1.0 - fx) + image[k, j1, i1] * fx
    c10 = image[k1, j, i] * (1.0 - fx) + image[k1, j, i1] * fx
    c11 = image[k1, j1, i] * (1.0 - fx) + image[k1, j1, i1] * fx
    out[v] = (c00 * (1.0 - fy) + c01 * fy) * (1.0 - fz) + (c10 * (1.0 - fy) + c11 * fy) * fz
