"""Why the solves of ``breastbiomech bench optimise`` fail (issue 25, point 4): each failed
parameter set of a fit's log is solved again with the load 1, 4 and 16 times slower, and where
and when its first element inverts is reported.

    breastbiomech bench optimise --device cuda --out FIT --json
    python benchmarks/optimise_failures.py FIT [--device cuda] [--json OUT.json]

A set whose inversion moves to a later point of the load (or away) when the load is slower is a
numerical failure (the loading's transient); one that inverts at the same load fraction whatever
the pace lies on the quasi-static path: a physical failure of that parameter set on that mesh.
The bench's case is rebuilt with its default geometry (radii 70/60/65 mm, 4 mm cubes); nothing
is asserted.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np

from BreastBiomechLib import labels
from BreastBiomechLib.cli.bench import BENCH_TRUTH
from BreastBiomechLib.optimisation import FittingProblem, ParameterSpace
from BreastBiomechLib.optimisation.synthetic import measured_at, synthetic_case
from BreastBiomechLib.solver import DynamicRelaxation
from BreastBiomechLib.solver.tled import MM, characteristic_lengths, shape_derivatives, wave_modulus

PACES = (1, 4, 16)
_AT = re.compile(r"at step (\d+) .* first element (\d+)")


def load_iterations(problem: FittingProblem, materials, relaxation: DynamicRelaxation) -> int:
    """The load iterations the solver gives one model (as in ``solve_batch``)."""
    model = problem.model
    nodes = model.mesh.nodes * MM
    _, vol = shape_derivatives(nodes, model.mesh.tets)
    length = characteristic_lengths(nodes, model.mesh.tets, vol)
    mat = materials.long_term()
    travel = max(np.abs(p.displacement).max() for p in model.loading.plates)
    return relaxation.load_iterations_for(travel, float(np.max(np.sqrt(wave_modulus(mat) / mat.mu))),
                                          float(np.median(length)), model.safety)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("fit", help="the --out folder of `breastbiomech bench optimise`")
    parser.add_argument("--device", default=None)
    parser.add_argument("--radii", type=float, nargs=3, default=(70.0, 60.0, 65.0))
    parser.add_argument("--element-mm", type=float, default=4.0)
    parser.add_argument("--voxel-mm", type=float, nargs=3, default=(1.0, 1.0, 2.5), help="the bench's voxel size (mm)")
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--json", help="write every failure's figures here")
    args = parser.parse_args()

    evaluations = [json.loads(line) for line in (Path(args.fit) / "evaluations.jsonl").read_text().splitlines()
                   if line.strip()]
    failed = [e for e in evaluations if e["status"] != "completed"]
    print(f"{len(failed)} of {len(evaluations)} solves failed; statuses "
          f"{sorted({e['status'] for e in failed})}", flush=True)
    case = synthetic_case(tuple(args.radii), element_mm=args.element_mm, voxel_mm=tuple(args.voxel_mm),
                          muscle_mm=10.0, tumour_mm=0.3 * args.radii[0])
    space = ParameterSpace.for_model("aniso-hetero", ["fat", "glandular", "muscle", "tumour"])
    relaxation = DynamicRelaxation()
    measured = measured_at(case, space, BENCH_TRUTH, relaxation, device=args.device)
    problem = FittingProblem(space, case.mesh, case.undeformed, measured, case.planes, relaxation=relaxation,
                             device=args.device)
    tissue = problem.tissue
    surface = case.mesh.point_data["surface"].astype(bool)
    rows = [{"values": e["values"], "z": e["z"], "paces": {}} for e in failed]
    for pace in PACES:
        slow = DynamicRelaxation(pace=float(pace))
        for start in range(0, len(rows), args.batch):
            chunk = rows[start:start + args.batch]
            solutions = problem.solve([r["z"] for r in chunk], relaxation=slow)
            for row, solution in zip(chunk, solutions):
                entry = {"status": solution.status, "steps": int(solution.steps)}
                found = _AT.search(solution.message)
                if found:
                    step, element = int(found.group(1)), int(found.group(2))
                    loads = load_iterations(problem, space.element_materials(row["z"], tissue), slow)
                    entry.update(step=step, load_iterations=loads, load_fraction=round(step / loads, 3),
                                 element_tissue=labels.tissue(int(tissue[element])).name,
                                 element_on_surface=bool(surface[case.mesh.tets[element]].any()),
                                 element_centre_mm=[round(float(v), 1)
                                                    for v in case.mesh.nodes[case.mesh.tets[element]].mean(axis=0)])
                row["paces"][str(pace)] = entry
            print(f"pace {pace}: solved {min(start + args.batch, len(rows))} of {len(rows)}", flush=True)
    for row in rows:
        passes = [p for p in PACES if row["paces"][str(p)]["status"] == "completed"]
        row["class"] = (f"numerical (passes at pace {passes[0]})" if passes[0] > 1 else "not reproduced (passes again at pace 1)") if passes else "physical"
        v = row["values"]
        ratios = {t: round(v[f"{t}.eta"] / (v.get(f"{t}.E", 10e3) / (2 * (1 + v[f"{t}.nu"]))), 2)
                  for t in ("fat", "glandular", "muscle", "tumour")}
        row["eta_over_mu"] = ratios
        print(json.dumps({"class": row["class"], "eta_over_mu": ratios,
                          "first": {p: {k: row["paces"][p].get(k) for k in ("status", "load_fraction", "element_tissue",
                                                                            "element_on_surface")}
                                    for p in row["paces"]}}), flush=True)
    counts = {}
    for row in rows:
        counts[row["class"].split(" (")[0]] = counts.get(row["class"].split(" (")[0], 0) + 1
    print(json.dumps({"failed": len(rows), "classes": counts}))
    if args.json:
        Path(args.json).write_text(json.dumps({"failures": rows, "classes": counts}, indent=1))


if __name__ == "__main__":
    main()
