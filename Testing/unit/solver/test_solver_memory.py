"""A solve that would not fit in memory is refused before anything is allocated (issue 28,
resource limits): the estimate of what ``solve_batch`` allocates, the refusal with the figures and
the largest batch that fits, on warp's CPU device."""

from __future__ import annotations

import numpy as np
import pytest

from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression
from BreastBiomechLib.solver.memory import SolveSize, TooLargeForMemory, check_fits, free_bytes


def test_the_estimate_grows_by_one_model_s_state_per_model():
    one = SolveSize(1, 30_000, 160_000, 30_000, 0, 2_000, 2)
    two = SolveSize(2, 30_000, 160_000, 30_000, 0, 2_000, 2)
    eight = SolveSize(8, 30_000, 160_000, 30_000, 0, 2_000, 2)
    per_model = two.device_bytes() - one.device_bytes()
    assert eight.device_bytes() - one.device_bytes() == 7 * per_model
    # the shared mesh is counted once, not per model
    assert one.device_bytes() - per_model > 0
    # visco terms add their state per element and model
    assert SolveSize(1, 30_000, 160_000, 30_000, 2).device_bytes() > one.device_bytes()


def test_the_host_s_free_memory_is_read():
    import warp as wp

    wp.init()
    free = free_bytes(wp.get_device("cpu"))
    assert free is None or free > 0


def test_a_batch_too_large_for_the_limit_is_refused_with_the_batch_that_fits():
    import warp as wp

    from BreastBiomechLib.solver import solve_batch

    wp.init()
    model = hemi_ellipsoid_compression(20.0)
    n, m = len(model.mesh.nodes), len(model.mesh.tets)
    one = SolveSize(1, n, m, n, 0, sum(len(p.slave_nodes) for p in model.loading.plates), 2)
    limit = int(2.5 * (one.device_bytes() + one.host_bytes()))
    with pytest.raises(TooLargeForMemory, match=r"solve of 4 model\(s\) on .* needs about .* GB, and the memory "
                                                r"limit given is .* solve at most 2 model\(s\) at once"):
        solve_batch(model, [model.materials] * 4, device="cpu", memory_limit_bytes=limit)
    with pytest.raises(TooLargeForMemory, match="use a coarser mesh"):
        solve_batch(model, [model.materials], device="cpu", memory_limit_bytes=1000)
    # a limit it fits under: the solve runs
    solution = solve_batch(model, [model.materials] * 2, device="cpu", memory_limit_bytes=limit)[0]
    assert solution.ok, solution.message


def test_a_refusal_is_a_value_error_the_command_line_reports_in_one_line():
    import warp as wp

    wp.init()
    with pytest.raises(ValueError):
        check_fits(SolveSize(10_000, 10**6, 6 * 10**6, 10**6), wp.get_device("cpu"), limit_bytes=10**9)


def test_warping_onto_a_grid_too_large_for_the_limit_is_refused_before_it_allocates():
    """The predicted image's grid (issue 28, resource limits): the estimate counts a position,
    flag and value per output voxel and the undeformed image, so a grid beyond the limit is
    refused with the voxel counts, and one within it warps."""
    import SimpleITK as sitk
    import warp as wp

    from BreastBiomechLib.solver.memory import warp_bytes
    from BreastBiomechLib.warping.predict import ImageWarper

    wp.init()
    mesh = hemi_ellipsoid_compression(20.0).mesh
    image = sitk.Image([40, 40, 20], sitk.sitkFloat32)
    image.SetOrigin([float(v) for v in mesh.nodes.min(axis=0)])
    image.SetSpacing([float(v) for v in np.ptp(mesh.nodes, axis=0) / [39, 39, 19]])
    needed = warp_bytes(32_000, 32_000, len(mesh.nodes), len(mesh.tets), on_cuda=False)
    assert needed >= 32_000 * 28
    with pytest.raises(TooLargeForMemory, match="onto a grid of 32000 voxels needs about .* crop or resample"):
        ImageWarper(mesh, image, image, device="cpu", memory_limit_bytes=needed - 1)
    warper = ImageWarper(mesh, image, image, device="cpu", memory_limit_bytes=needed)
    assert warper.warp(np.zeros_like(mesh.nodes)).shape == (32_000,)
