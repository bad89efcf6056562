"""A fit's solves again, to see why some fail and what other relaxation settings change
(issue 25, point 4), on the log of ``breastbiomech bench optimise --out FIT``:

    python benchmarks/fit_solves.py failures FIT [--device cuda] [--json OUT.json]
    python benchmarks/fit_solves.py workload FIT [--device cuda] [--pace 1 2 3] [--batches] [--pack-at 0.5]

``failures`` solves each failed parameter set again with its load 1, 4 and 16 times slower and
reports when (the fraction of the load) and where (the first inverted element: tissue, surface,
centre) it fails. A set that passes once the load is slower is a numerical failure (the
loading's transient); one that inverts at the same load fraction whatever the pace lies on the
quasi-static path: a physical failure of that parameter set on that mesh.

``workload`` solves all the fit's sets in the fit's own batches under each setting, so that
settings are compared on one workload rather than on optimiser paths that part after the first
generation, and prints one JSON line per setting: failures by status, the solves' wall seconds,
the iterations (median, largest) and the slowest batch; ``--batches`` also prints a line per
batch (its seconds, each model's iterations and status), which shows how long a batch waits on its
slowest model. ``--pack-at F`` sets the fraction of a batch still moving at which the solver packs
it down to those models (``solver.batch_run.PACK_AT``; 0 never packs).

The bench's case is rebuilt (``bench_fitting_problem``, default geometry: radii 70/60/65 mm,
4 mm cubes); nothing is asserted.
"""

from __future__ import annotations

import argparse
import collections
import json
import re
import time
from pathlib import Path

import numpy as np

from BreastBiomechLib import labels
from BreastBiomechLib.cli.bench import bench_fitting_problem
from BreastBiomechLib.optimisation.record import read_evaluations
from BreastBiomechLib.solver import DynamicRelaxation, batch_run, host_setup

PACES = (1, 4, 16)
_AT = re.compile(r"at step (\d+) .* first element (\d+)")


def load_iterations(problem, z, relaxation: DynamicRelaxation) -> int:
    """The load iterations the solver gives the set at unit position ``z`` of ``problem``."""
    materials = problem.space.element_materials(z, problem.tissue).long_term()
    return int(host_setup.relaxation_load_iterations(problem.model, [materials], [problem.model.loading.plates], relaxation)[0])


def failures(problem, evaluations, batch: int, out: str | None) -> None:
    failed = [e for e in evaluations if e.status != "completed"]
    print(f"{len(failed)} of {len(evaluations)} solves failed: "
          f"{dict(collections.Counter(e.status for e in failed))}", flush=True)
    mesh, tissue = problem.mesh, problem.tissue
    surface = mesh.point_data["surface"].astype(bool)
    rows = [{"values": e.values, "z": e.z, "paces": {}} for e in failed]
    for pace in PACES:
        slow = DynamicRelaxation(pace=float(pace))
        for start in range(0, len(rows), batch):
            chunk = rows[start:start + batch]
            for row, solution in zip(chunk, problem.solve([r["z"] for r in chunk], relaxation=slow)):
                entry = {"status": solution.status, "steps": int(solution.steps)}
                found = _AT.search(solution.message)
                if found:
                    step, element = int(found.group(1)), int(found.group(2))
                    loads = load_iterations(problem, row["z"], slow)
                    entry.update(step=step, load_iterations=loads, load_fraction=round(step / loads, 3),
                                 element_tissue=labels.tissue(int(tissue[element])).name,
                                 element_on_surface=bool(surface[mesh.tets[element]].any()),
                                 element_centre_mm=[round(float(v), 1) for v in mesh.nodes[mesh.tets[element]].mean(axis=0)])
                row["paces"][str(pace)] = entry
        print(f"pace {pace}: {len(rows)} solved again", flush=True)
    for row in rows:
        passes = [p for p in PACES if row["paces"][str(p)]["status"] == "completed"]
        row["class"] = ("physical" if not passes else "not reproduced (passes again at pace 1)" if passes[0] == 1
                        else f"numerical (passes at pace {passes[0]})")
        print(json.dumps({"class": row["class"], "at": {p: {k: row["paces"][p].get(k) for k in
                                                             ("status", "load_fraction", "element_tissue")}
                                                         for p in row["paces"]}}), flush=True)
    counts = dict(collections.Counter(row["class"].split(" (")[0] for row in rows))
    print(json.dumps({"failed": len(rows), "classes": counts}))
    if out:
        Path(out).write_text(json.dumps({"failures": rows, "classes": counts}, indent=1))


def workload(problem, evaluations, batch: int, paces, load: int, most: int, per_batch: bool) -> None:
    problem.solve([evaluations[0].z], relaxation=DynamicRelaxation(max_iterations=1200))  # compile, warm up
    logged = dict(collections.Counter(e.status for e in evaluations))
    for pace in paces:
        relaxation = DynamicRelaxation(load_iterations=load, max_iterations=most, pace=pace)
        statuses, steps, seconds = [], [], []
        for start in range(0, len(evaluations), batch):
            began = time.perf_counter()
            solutions = problem.solve([e.z for e in evaluations[start:start + batch]], relaxation=relaxation)
            seconds.append(time.perf_counter() - began)
            if per_batch:
                print(json.dumps({"pace": pace, "first": start, "seconds": round(seconds[-1], 3),
                                  "iterations": [int(s.steps) for s in solutions],
                                  "statuses": [s.status for s in solutions]}), flush=True)
            statuses += [s.status for s in solutions]
            steps += [s.steps for s in solutions if s.ok]
        counts = collections.Counter(statuses)
        print(json.dumps({"pace": pace, "pack_at": batch_run.PACK_AT, "load_iterations": load, "max_iterations": most,
                          "solves": len(statuses),
                          "failed": len(statuses) - counts["completed"], "statuses": dict(counts),
                          "logged_statuses": logged, "solve_seconds": round(sum(seconds), 2),
                          "slowest_batch_s": round(max(seconds), 2),
                          "iterations_median": int(np.median(steps)) if steps else None,
                          "iterations_max": int(max(steps)) if steps else None}), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=("failures", "workload"))
    parser.add_argument("fit", help="the --out folder of `breastbiomech bench optimise`")
    parser.add_argument("--device", default=None)
    parser.add_argument("--radii", type=float, nargs=3, default=(70.0, 60.0, 65.0), help="the bench's (mm)")
    parser.add_argument("--element-mm", type=float, default=4.0, help="the bench's cube size (mm)")
    parser.add_argument("--stair-corners", action="store_true",
                        help="the mesh's stair corners left protruding (a fit made with bench optimise --stair-corners)")
    parser.add_argument("--batch", type=int, default=16, help="solves per batch (workload: the fit's population)")
    parser.add_argument("--json", help="failures: write every failure's figures here")
    parser.add_argument("--pace", type=float, nargs="+", default=[1.0], help="workload: load this many times slower")
    parser.add_argument("--load-iterations", type=int, default=1000, help="workload: the relaxation's minimum load")
    parser.add_argument("--max-iterations", type=int, default=50_000, help="workload: the relaxation's cap")
    parser.add_argument("--first", type=int, default=None, help="workload: only the first this many solves")
    parser.add_argument("--batches", action="store_true", help="workload: a line per batch too")
    parser.add_argument("--pack-at", type=float, default=None,
                        help="workload: pack a batch once this fraction of it or less still moves (0: never)")
    args = parser.parse_args()

    evaluations = read_evaluations(Path(args.fit) / "evaluations.jsonl")
    if args.pack_at is not None:
        batch_run.PACK_AT = args.pack_at
    # the failures' solves need no similarity: the undeformed image stands in for the measured one
    problem = bench_fitting_problem(args.radii, args.element_mm, device=args.device, measured=False,
                                    pull_corners=not args.stair_corners)
    if args.what == "failures":
        failures(problem, evaluations, args.batch, args.json)
    else:
        workload(problem, evaluations[:args.first], args.batch, args.pace, args.load_iterations, args.max_iterations,
                 args.batches)


if __name__ == "__main__":
    main()
