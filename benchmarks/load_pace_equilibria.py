"""Which equilibrium dynamic relaxation finds as its load is applied more slowly (issue 25,
point 3): ``bench optimise``'s fitting problem at its truth (the synthetic breast of radii
70/60/65 mm in 4 mm cubes, two plates closing 17.5 mm each) solved with the load 1, 1.5, 2, 4
and 8 times slower (``DynamicRelaxation.pace``, tolerance 0.002 mm), and with the plates closing
each ``--fractions`` of their travel (one batch per pace). Prints one JSON line per fraction and
pace: status, iterations, the largest nodal distance (mm) to the first pace's answer at that
fraction, how many nodes lie more than 0.1 mm from it, where the largest distance is (reference
position, mm, LPS) and both displacements there, the plates' normal forces (N) and the internal
energy (J). Two answers far apart with different energies are two equilibria; the fractions show
where along the compression the paths part. Nothing is asserted.

    python benchmarks/load_pace_equilibria.py [--device cuda] [--paces 1 1.5 2 4 8] [--fractions 0.5 0.8 1]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from BreastBiomechLib.cli.bench import BENCH_TRUTH, bench_fitting_problem
from BreastBiomechLib.solver import DynamicRelaxation, solve_batch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default=None, help="warp device (default: warp's)")
    parser.add_argument("--paces", type=float, nargs="+", default=(1.0, 1.5, 2.0, 4.0, 8.0))
    parser.add_argument("--fractions", type=float, nargs="+", default=(1.0,), help="of the plates' travel")
    args = parser.parse_args()
    problem = bench_fitting_problem(measured=False, device=args.device)
    model, nodes = problem.model, problem.mesh.nodes
    materials = problem.space.element_materials(problem.space.unit(BENCH_TRUTH), problem.tissue)
    travel = [[f * p.displacement for p in model.loading.plates] for f in args.fractions]
    first = None
    for pace in args.paces:
        relaxation = DynamicRelaxation(pace=pace, tolerance_mm=0.002, max_iterations=200_000)
        solutions = solve_batch(model, [materials] * len(travel), travel, device=args.device, relaxation=relaxation)
        first = first or solutions
        for fraction, s, f in zip(args.fractions, solutions, first):
            distance = np.abs(s.displacement - f.displacement).max(axis=1)
            at = int(distance.argmax())
            print(json.dumps({"fraction": fraction, "pace": pace, "status": s.status, "iterations": s.steps,
                              "largest_distance_mm": round(float(distance.max()), 4),
                              "nodes_over_0.1mm": int((distance > 0.1).sum()), "at_node_mm": nodes[at].round(1).tolist(),
                              "displacement_first_pace_mm": f.displacement[at].round(2).tolist(),
                              "displacement_mm": s.displacement[at].round(2).tolist(),
                              "plate_normal_forces_N": s.plate_normal_forces.round(3).tolist(),
                              "internal_energy_J": float(s.history["internal"][-1])}), flush=True)

if __name__ == "__main__":
    main()
