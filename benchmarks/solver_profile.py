"""Where a relaxation solve's device time goes (issue 25): warp's activity timing around one
``solve_batch`` of ``breastbiomech bench solver``'s model.

    python benchmarks/solver_profile.py --tets 160000 [--per-kernel | --alone] [--device cuda]

prints, per activity (graph launches, kernels, copies, memsets), the count, total and mean time.
The solver replays its steps and samples as CUDA graphs, so the default view gives the time per
graph of ten steps (two for an interval's rest); ``--per-kernel`` solves again with the graphs
replaced by direct launches (for this script only) to give each step kernel's time, launch and
timing overhead included (about 8 µs per launch on an H100). ``--alone`` records the step kernels' last launches in a
solve and replays each kernel by itself, 20 launches in a CUDA graph (µs per launch, wall clock,
the best of three), then the whole step in graphs of 2 and of 10 steps: the figures to set
against ``benchmarks/minimal_tled_step.py``'s kernels (each from a fresh solve's converged state,
its frozen flag cleared, so the kernels do a moving model's work). A CUDA device is needed;
nothing is asserted.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import time

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


def _replayed(launches: list, repeats: int = 20, replays: int = 100) -> float:
    """µs per repeat of ``launches`` ((kernel, dim, inputs, block_dim) in order), replayed as a
    CUDA graph of ``repeats`` repeats, after a warm-up; the best of three."""
    with wp.ScopedCapture() as capture:
        for _ in range(repeats):
            for kernel, dim, inputs, block_dim in launches:
                wp.launch(kernel, dim, inputs, block_dim=block_dim)
    best = float("inf")
    for _ in range(3):
        for _ in range(5):
            wp.capture_launch(capture.graph)
        wp.synchronize()
        started = time.perf_counter()
        for _ in range(replays):
            wp.capture_launch(capture.graph)
        wp.synchronize()
        best = min(best, 1e6 * (time.perf_counter() - started) / (repeats * replays))
    return best


def argument(record: tuple, name: str):
    """The value a recorded launch (kernel, dim, inputs, block_dim) passed for argument ``name``."""
    kernel, _, inputs, _ = record
    return inputs[[a.label for a in kernel.adj.args].index(name)]


def _recorded_step(model, device: str) -> tuple:
    """A relaxation solve of ``model`` and its step kernels' last launches (kernel, dim, inputs,
    block_dim): its element forces, ANP sums and node update, in a step's order."""
    recorded = {}
    launch = wp.launch

    def recording(kernel, dim, inputs=None, *args, **kwargs):
        name = kernel.func.__name__
        record = (kernel, dim, list(inputs or []), kwargs.get("block_dim", 256))
        if name == "element_forces" and argument(record, "update_state") == 1:  # a step's, not a probe's
            recorded[name] = record
        elif name == "nodal_pressure":  # kept per ANP buffer: the step's is the node kernel's
            recorded.setdefault(name, {})[id(argument(record, "anp_sums"))] = record
        elif name == "advance_nodes":
            recorded[name] = record
        return launch(kernel, dim, inputs, *args, **kwargs)

    wp.launch = recording
    try:
        solution = solve_batch(model, [model.materials], device=device, relaxation=DynamicRelaxation())[0]
    finally:
        wp.launch = launch
    nodes = recorded["advance_nodes"]
    return solution, [recorded["nodal_pressure"][id(argument(nodes, "anp_sums"))], recorded["element_forces"], nodes]


def alone(tets: int, device: str) -> None:
    """The step kernels one by one, and the step, replayed as CUDA graphs (see the docstring),
    each from a fresh solve's converged state (replays move the state: a kernel replayed alone
    piles up forces or sums that the next measurement must not start from)."""
    wp.init()
    model = hemi_ellipsoid_compression(_hemi_ellipsoid_spacing(tets), compression=0.25)
    for position in (1, 0, 2, None):  # element forces, ANP sums, node update, the step
        solution, step = _recorded_step(model, device)
        if position == 1:
            print(f"{len(model.mesh.tets)} tets, {solution.steps} iterations; each kernel alone, µs per launch:")
        argument(step[1], "inverted").zero_()  # the converged model moves again
        argument(step[0], "anp_sums").zero_()  # the node kernel clears them after use; begin cleared
        if position is None:
            for repeats in (2, 10):  # the solver replays graphs of ten steps (two for an interval's rest)
                print(f"  the step, in graphs of {repeats:2d} steps  {_replayed(step, repeats=repeats):7.2f}")
            continue
        record = step[position]
        registers = wp.get_cuda_kernel_properties(record[0], device)["register_count"]
        print(f"  {record[0].func.__name__:16s} {_replayed([record]):7.2f}  ({record[1]} threads in blocks of "
              f"{record[3]}, {registers} registers)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tets", type=int, default=160_000, help="about this many tets (the bench's mesh)")
    how = parser.add_mutually_exclusive_group()
    how.add_argument("--per-kernel", action="store_true", help="time each kernel (graphs replaced by launches)")
    how.add_argument("--alone", action="store_true", help="replay each step kernel by itself in a CUDA graph")
    parser.add_argument("--device", default="cuda", help="a CUDA warp device (default cuda)")
    args = parser.parse_args()
    if not wp.get_device(args.device).is_cuda:
        parser.error("activity timing needs a CUDA device")
    if args.alone:
        alone(args.tets, args.device)
    else:
        profile(args.tets, args.device, args.per_kernel)


if __name__ == "__main__":
    main()
