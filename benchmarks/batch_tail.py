"""What a batch's iterations cost by the count of its models still moving (issue 25), on the log of
``breastbiomech bench optimise --out FIT``:

    python benchmarks/batch_tail.py FIT [--device cuda] [--first 432 448]

Each chosen fit batch (16 solves from ``--first``) is solved again with a timestamp at every
sample (``solve_batch``'s ``progress``), then its slowest set alone and with the batch's three
fastest; one JSON line per solve gives each model's iterations and, per count of models still
moving, the median microseconds per iteration and the samples it held. A model left moving in a
batch steps in the batch's layout (its state interleaved with the others'), which is what this
measures against the same model alone. The bench's case is rebuilt (``bench_fitting_problem``,
default geometry, pulled corners unless ``--stair-corners``); nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from BreastBiomechLib.cli.bench import bench_fitting_problem
from BreastBiomechLib.optimisation.record import read_evaluations
from BreastBiomechLib.solver import DynamicRelaxation, solve_batch


def timed(problem, positions, relaxation: DynamicRelaxation) -> dict:
    """One batched solve of ``positions``: iterations per model, us per iteration by moving count."""
    materials = [problem.space.element_materials(z, problem.tissue) for z in positions]
    stamps = []
    solutions = solve_batch(problem.model, materials, device=problem.device, relaxation=relaxation,
                            progress=lambda fraction: stamps.append(time.perf_counter()))
    iterations = np.array([s.steps for s in solutions])
    done = relaxation.update_every * np.arange(1, len(stamps) + 1)
    moving = np.array([int((iterations > d).sum()) for d in done])[1:]
    per_iteration = np.diff(stamps) / relaxation.update_every * 1e6
    return {"models": len(positions), "iterations": iterations.tolist(),
            "us_per_iteration_by_moving": {int(n): [round(float(np.median(per_iteration[moving == n])), 1),
                                                    int(np.sum(moving == n))] for n in sorted(set(moving))}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("fit", help="the --out folder of `breastbiomech bench optimise`")
    parser.add_argument("--device", default=None)
    parser.add_argument("--first", type=int, nargs="+", default=[432, 448], help="the batches' first solves")
    parser.add_argument("--batch", type=int, default=16, help="the fit's population")
    parser.add_argument("--stair-corners", action="store_true", help="a fit made with bench optimise --stair-corners")
    args = parser.parse_args()

    evaluations = read_evaluations(Path(args.fit) / "evaluations.jsonl")
    problem = bench_fitting_problem(device=args.device, measured=False, pull_corners=not args.stair_corners)
    relaxation = DynamicRelaxation()
    problem.solve([evaluations[0].z], relaxation=DynamicRelaxation(max_iterations=1200))  # compile, warm up
    for first in args.first:
        positions = [e.z for e in evaluations[first:first + args.batch]]
        whole = timed(problem, positions, relaxation)
        print(json.dumps({"first": first, **whole}), flush=True)
        order = np.argsort(whole["iterations"])
        slowest = int(order[-1])
        for others in (0, 3):
            chosen = [slowest] + [int(i) for i in order[:others]]
            print(json.dumps({"first": first, **timed(problem, [positions[i] for i in chosen], relaxation)}), flush=True)


if __name__ == "__main__":
    main()
