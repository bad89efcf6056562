"""How close warm-started and cold relaxation solves end to the static solution (issue 25).

The benchmarks' hemi-ellipsoid breast (``breastbiomech bench solver``'s mesh at ``--tets``)
with its shear modulus times 1, 0.5, 0.3 and 2 (the bulk modulus kept), solved three ways in
batches: with a tolerance of 0.0005 mm (the reference), cold with the default 0.01 mm, and warm
from the equilibrium of the shear modulus times ``--start`` (default 1.2). Prints one JSON line
per variant: iterations cold and warm, and the largest nodal distance (mm) of each to the
reference and to each other.

    python benchmarks/warm_start_check.py [--tets 160000] [--device cuda] [--start 1.2]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from BreastBiomechLib.cli.bench import _hemi_ellipsoid_spacing
from BreastBiomechLib.solver import DynamicRelaxation, solve_batch
from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression
from BreastBiomechLib.solver.warm import WarmStart

FACTORS = (1.0, 0.5, 0.3, 2.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tets", type=int, default=160_000)
    parser.add_argument("--device", default=None, help="warp device (default: warp's)")
    parser.add_argument("--start", type=float, default=1.2, help="the warm start's shear modulus factor")
    args = parser.parse_args()
    relaxation = DynamicRelaxation(tolerance_mm=0.01)
    model = hemi_ellipsoid_compression(_hemi_ellipsoid_spacing(args.tets), compression=0.25)
    base = model.materials

    def shear_times(factor):
        return type(base)(base.mu * factor, base.kappa, base.eta, base.fibre, base.density)

    variants = [shear_times(f) for f in FACTORS]
    reference = solve_batch(model, variants, device=args.device,
                            relaxation=DynamicRelaxation(tolerance_mm=0.0005, max_iterations=200_000))
    cold = solve_batch(model, variants, device=args.device, relaxation=relaxation)
    start = solve_batch(model, [shear_times(args.start)], device=args.device, relaxation=relaxation)[0]
    warm = solve_batch(model, variants, device=args.device, relaxation=relaxation,
                       warm_start=WarmStart.from_solution(start))
    for factor, r, c, w in zip(FACTORS, reference, cold, warm):
        print(json.dumps({"tets": len(model.mesh.tets), "mu_factor": factor, "start_mu_factor": args.start,
                          "cold_steps": c.steps, "warm_steps": w.steps, "warm_status": w.status,
                          "cold_error_mm": float(np.abs(c.displacement - r.displacement).max()),
                          "warm_error_mm": float(np.abs(w.displacement - r.displacement).max()),
                          "warm_minus_cold_mm": float(np.abs(w.displacement - c.displacement).max())}))


if __name__ == "__main__":
    main()
