"""A fit's solves again under other relaxation settings (issue 25): the parameter sets of a
``breastbiomech bench optimise --out FIT`` log, solved in the fit's own batches, so that
settings are compared on one workload rather than on optimiser paths that part after the first
generation.

    python benchmarks/fit_workload.py FIT [--device cuda] [--pace 1 2] [--load-iterations 1000]
        [--max-iterations 50000] [--population 16]

prints one JSON line per setting: solves, failures by status, wall seconds of the solves, the
iterations (median and largest) and the largest batch's wall time. The bench's case is rebuilt
with its default geometry (radii 70/60/65 mm, 4 mm cubes); nothing is asserted.
"""

from __future__ import annotations

import argparse
import collections
import json
import time
from pathlib import Path

import numpy as np

from BreastBiomechLib.optimisation import FittingProblem, ParameterSpace
from BreastBiomechLib.optimisation.synthetic import synthetic_case
from BreastBiomechLib.solver import DynamicRelaxation


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("fit", help="the --out folder of `breastbiomech bench optimise`")
    parser.add_argument("--device", default=None)
    parser.add_argument("--radii", type=float, nargs=3, default=(70.0, 60.0, 65.0))
    parser.add_argument("--element-mm", type=float, default=4.0)
    parser.add_argument("--population", type=int, default=16, help="the fit's batch size")
    parser.add_argument("--pace", type=float, nargs="+", default=[1.0])
    parser.add_argument("--load-iterations", type=int, default=1000)
    parser.add_argument("--max-iterations", type=int, default=50_000)
    parser.add_argument("--first", type=int, default=None, help="only the first this many solves")
    args = parser.parse_args()

    evaluations = [json.loads(line) for line in (Path(args.fit) / "evaluations.jsonl").read_text().splitlines()
                   if line.strip()][:args.first]
    case = synthetic_case(tuple(args.radii), element_mm=args.element_mm, voxel_mm=(4.0, 4.0, 4.0),
                          muscle_mm=10.0, tumour_mm=0.3 * args.radii[0])
    space = ParameterSpace.for_model("aniso-hetero", ["fat", "glandular", "muscle", "tumour"])
    problem = FittingProblem(space, case.mesh, case.undeformed, case.undeformed, case.planes, device=args.device)
    problem.solve([evaluations[0]["z"]], relaxation=DynamicRelaxation(max_iterations=1200))  # compile, warm up
    logged = collections.Counter(e["status"] for e in evaluations)
    for pace in args.pace:
        relaxation = DynamicRelaxation(load_iterations=args.load_iterations, max_iterations=args.max_iterations,
                                       pace=pace)
        statuses, steps, batch_seconds = [], [], []
        for start in range(0, len(evaluations), args.population):
            chunk = evaluations[start:start + args.population]
            began = time.perf_counter()
            solutions = problem.solve([e["z"] for e in chunk], relaxation=relaxation)
            batch_seconds.append(time.perf_counter() - began)
            statuses += [s.status for s in solutions]
            steps += [s.steps for s in solutions if s.ok]
        counts = collections.Counter(statuses)
        print(json.dumps({"pace": pace, "load_iterations": args.load_iterations,
                          "max_iterations": args.max_iterations, "solves": len(statuses),
                          "failed": len(statuses) - counts["completed"], "statuses": dict(counts),
                          "logged_statuses": dict(logged), "solve_seconds": round(sum(batch_seconds), 2),
                          "slowest_batch_s": round(max(batch_seconds), 2),
                          "iterations_median": int(np.median(steps)) if steps else None,
                          "iterations_max": int(max(steps)) if steps else None}), flush=True)


if __name__ == "__main__":
    main()
