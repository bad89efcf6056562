"""Where a relaxation solve's device time goes (issue 25): warp's activity timing around one
``solve_batch`` of ``breastbiomech bench solver``'s model.

    python benchmarks/solver_profile.py --tets 160000 [--batch B] [--alone] [--device cuda]
    python benchmarks/solver_profile.py --ncu KERNELS.csv --batch B

The first prints, per activity (graph launches, kernels, copies, memsets), the count, total and
mean time, and the total per model and iteration. The solver replays its steps and samples as
CUDA graphs, so this gives the time per graph of ten steps (two for an interval's rest).
``--alone`` (a lone model) records the step kernels' last launches in a solve and replays each
kernel by itself, 20 launches in a CUDA graph (µs per launch, wall clock, the best of three),
then the whole step in graphs of 2 and of 10 steps: the figures to set against
``benchmarks/minimal_tled_step.py``'s kernels (each from a fresh solve's converged state, its
frozen flag cleared, so the kernels do a moving model's work). A CUDA device is needed; nothing is
asserted.

Each kernel's time inside the graphs comes from Nsight Compute, which times the kernels of a
graph one by one: run this script under it for a window of launches and summarise the CSV with
``--ncu`` (here, no GPU needed): per kernel the count, mean and share of the window's kernel time
and the time per model and step (the window's steps counted by its node-update launches)::

    ncu --clock-control none --metrics gpu__time_duration.sum --launch-skip 12000 \
        --launch-count 700 --csv --log-file kernels.csv \
        python benchmarks/solver_profile.py --tets 160000 --batch 64

The warm-up solve is some 4 000 launches, so a skip of 12 000 lands in the middle of the timed
solve; 700 launches hold about 220 steps and one relaxation sample. Nsight Compute empties the
caches before each kernel it times, so a kernel that reads what the one before it wrote looks
somewhat slower than it runs in the solver.
"""

from __future__ import annotations

import argparse
import collections
import csv

import warp as wp

from BreastBiomechLib.cli.bench import _hemi_ellipsoid_spacing, bench_parameter_sets
from BreastBiomechLib.solver import DynamicRelaxation, solve_batch
from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression
from graph_replay import argument, recorded_launches, replayed  # this folder's
from kernel_registers import kernel_name  # this folder's: warp's CUDA symbol -> the kernel's name


def profile(tets: int, device: str, batch: int = 1) -> None:
    wp.init()
    model = hemi_ellipsoid_compression(_hemi_ellipsoid_spacing(tets), compression=0.25)
    solve_batch(model, [model.materials], device=device, relaxation=DynamicRelaxation(max_iterations=1200))  # warm
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    solution = solve_batch(model, bench_parameter_sets(model.materials, batch), device=device,
                           relaxation=DynamicRelaxation())[0]
    results = wp.timing_end()
    totals = collections.defaultdict(lambda: [0, 0.0])
    for r in results:
        totals[r.name][0] += 1
        totals[r.name][1] += r.elapsed
    print(f"{len(model.mesh.tets)} tets, batch of {batch}, {solution.steps} iterations, solve "
          f"{solution.wall_time:.4f} s; per activity: count x mean = "
          "total, and the total per model and iteration")
    for name, (count, ms) in sorted(totals.items(), key=lambda item: -item[1][1])[:15]:
        print(f"  {name[:56]:56s} {count:7d} x {1000 * ms / count:9.2f} us = {ms:9.3f} ms"
              f" ({1000 * ms / solution.steps / batch:6.3f} us)")


def _recorded_step(model, device: str) -> tuple:
    """A relaxation solve of ``model`` and its step kernels' last launches (kernel, dim, inputs,
    block_dim): its element forces, ANP sums and node update, in a step's order."""
    recorded = {}
    with recorded_launches() as launches:
        solution = solve_batch(model, [model.materials], device=device, relaxation=DynamicRelaxation())[0]
    for record in launches:
        name = record[0].func.__name__
        if name == "element_forces" and argument(record, "update_state") == 1:  # a step's, not a probe's
            recorded[name] = record
        elif name == "nodal_pressure":  # kept per ANP buffer: the step's is the node kernel's
            recorded.setdefault(name, {})[id(argument(record, "anp_sums"))] = record
        elif name == "advance_nodes":
            recorded[name] = record
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
                print(f"  the step, in graphs of {repeats:2d} steps  {replayed(step, repeats=repeats):7.2f}")
            continue
        record = step[position]
        registers = wp.get_cuda_kernel_properties(record[0], device)["register_count"]
        print(f"  {record[0].func.__name__:16s} {replayed([record]):7.2f}  ({record[1]} threads in blocks of "
              f"{record[3]}, {registers} registers)")


def ncu_summary(path: str, batch: int) -> None:
    """Per kernel of an Nsight Compute CSV (``--metrics gpu__time_duration.sum``, see the
    docstring): launches, mean time, share of the window's kernel time and time per model and
    step, the steps counted by the window's ``advance_nodes`` launches."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    header = next((i for i, row in enumerate(rows) if row[:1] == ["ID"]), None)
    if header is None:
        raise SystemExit(f"{path}: no Nsight Compute CSV header (a row starting with ID); run ncu with --csv")
    names = rows[header]
    kernel, metric, unit, value = (names.index(c) for c in ("Kernel Name", "Metric Name", "Metric Unit",
                                                          "Metric Value"))
    scale = {"ns": 1e-3, "nsecond": 1e-3, "us": 1.0, "usecond": 1.0, "ms": 1e3, "msecond": 1e3}
    totals = collections.defaultdict(lambda: [0, 0.0])
    for row in rows[header + 1:]:
        if len(row) <= value or row[metric] != "gpu__time_duration.sum":
            continue
        name = kernel_name(row[kernel])
        totals[name][0] += 1
        if row[unit] not in scale:
            raise SystemExit(f"{path}: kernel times in {row[unit]!r}; expected one of {', '.join(scale)}")
        totals[name][1] += float(row[value].replace(",", "")) * scale[row[unit]]
    steps = totals["advance_nodes"][0]
    if steps == 0:
        raise SystemExit(f"{path}: no advance_nodes launch timed: the window holds no step of the solve")
    window = sum(us for _, us in totals.values())
    print(f"{path}: {steps} steps in the window, kernels {window / steps:.1f} us a step, "
          f"{window / steps / batch:.3f} us per model-step (batch of {batch})")
    for name, (count, us) in sorted(totals.items(), key=lambda item: -item[1][1]):
        print(f"  {name[:40]:40s} {count:5d} x {us / count:9.2f} us  {100 * us / window:5.1f} %  "
              f"{us / steps / batch:7.3f} us per model-step")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tets", type=int, default=160_000, help="about this many tets (the bench's mesh)")
    how = parser.add_mutually_exclusive_group()
    how.add_argument("--alone", action="store_true", help="replay each step kernel by itself in a CUDA graph")
    how.add_argument("--ncu", metavar="CSV", help="summarise Nsight Compute's kernel times (see the docstring)")
    parser.add_argument("--batch", type=int, default=1,
                        help="parameter sets solved together, as bench solver --batch (not with --alone)")
    parser.add_argument("--device", default="cuda", help="a CUDA warp device (default cuda)")
    args = parser.parse_args()
    if args.ncu:
        ncu_summary(args.ncu, args.batch)
        return
    if not wp.get_device(args.device).is_cuda:
        parser.error("activity timing needs a CUDA device")
    if args.alone and args.batch != 1:
        parser.error("--alone replays a lone model's step; leave out --batch")
    if args.alone:
        alone(args.tets, args.device)
    else:
        profile(args.tets, args.device, args.batch)


if __name__ == "__main__":
    main()
