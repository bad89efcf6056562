"""Where a relaxation solve's device time goes (issue 25): warp's activity timing around one
``solve_batch`` of ``breastbiomech bench solver``'s model.

    python benchmarks/solver_profile.py --tets 160000 [--per-kernel] [--device cuda]

prints, per activity (graph launches, kernels, copies, memsets), the count, total and mean time.
The solver replays its steps and samples as CUDA graphs, so the default view gives the time per
graph of two steps; ``--per-kernel`` solves again with the graphs replaced by direct launches
(for this script only) to give each step kernel's time, launch and timing overhead included
(about 8 µs per launch on an H100). A CUDA device is needed; nothing is asserted.
"""

from __future__ import annotations

import argparse
import collections
import contextlib

import warp as wp

from BreastBiomechLib.cli.bench import _hemi_ellipsoid_spacing
from BreastBiomechLib.solver import DynamicRelaxation, solve_batch, tled
from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression


class _NoGraph:
    graph = None


@contextlib.contextmanager
def _launch_directly(*args, **kwargs):
    """Stands in for wp.ScopedCapture: what would be captured runs at once, and no graph is made."""
    yield _NoGraph()


def profile(tets: int, device: str, per_kernel: bool) -> None:
    wp.init()
    model = hemi_ellipsoid_compression(_hemi_ellipsoid_spacing(tets), compression=0.25)
    solve_batch(model, [model.materials], device=device, relaxation=DynamicRelaxation(max_iterations=1200))  # warm
    if per_kernel:
        tled.wp.ScopedCapture = _launch_directly
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL if per_kernel else wp.TIMING_ALL)
    solution = solve_batch(model, [model.materials], device=device, relaxation=DynamicRelaxation())[0]
    results = wp.timing_end()
    totals = collections.defaultdict(lambda: [0, 0.0])
    for r in results:
        totals[r.name][0] += 1
        totals[r.name][1] += r.elapsed
    print(f"{len(model.mesh.tets)} tets, {solution.steps} iterations, solve {solution.wall_time:.4f} s"
          f"{' (direct launches)' if per_kernel else ''}")
    for name, (count, ms) in sorted(totals.items(), key=lambda item: -item[1][1])[:15]:
        print(f"  {name[:56]:56s} {count:7d} x {1000 * ms / count:9.2f} us = {ms:9.3f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tets", type=int, default=160_000, help="about this many tets (the bench's mesh)")
    parser.add_argument("--per-kernel", action="store_true", help="time each kernel (graphs replaced by launches)")
    parser.add_argument("--device", default="cuda", help="a CUDA warp device (default cuda)")
    args = parser.parse_args()
    if not wp.get_device(args.device).is_cuda:
        parser.error("activity timing needs a CUDA device")
    profile(args.tets, args.device, args.per_kernel)


if __name__ == "__main__":
    main()
