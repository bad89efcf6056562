"""What the solver's renumbering of a scattered mesh buys (solver/ordering.py; issue 25).

The benchmark breast of ``breastbiomech bench solver`` meshed by TetGen
(:func:`~BreastBiomechLib.mesh.primitives.smooth_hemi_ellipsoid_mesh` at ``--edge-mm``), in
TetGen's numbering, compressed 25 % between two plates and relaxed to rest: solved renumbered in
Z-order (:class:`~BreastBiomechLib.solver.ordering.SolverOrder`, whatever the device and batch)
and in the mesh's own order, one after the other, ``--repeat`` times each, on one device. Prints one
JSON line per solve (``solve_s``: ``Solution.wall_time``, the stepping loop; ``call_s``: the whole
``solve_batch`` call, set-up included), then the host time of the renumbering itself (codes,
renumbered model and materials) and the largest nodal difference between the two answers (mm).

    python benchmarks/mesh_order.py --device cuda [--batch 1] [--edge-mm 1.6077571432] [--mesh FILE.npz]

TetGen runs where the ``tetgen`` package is installed; ``--save FILE.npz`` keeps the mesh, and
``--mesh FILE.npz`` reads it instead (for a GPU machine without TetGen). Nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from BreastBiomechLib.cli.bench import BENCH_RADII_MM
from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.solver import DynamicRelaxation, solve_batch
from BreastBiomechLib.solver import ordering
from BreastBiomechLib.solver.cases import plate_compression


def tetgen_breast(edge_mm: float, path: str | None) -> TetMesh:
    if path:
        data = np.load(path)
        return TetMesh(data["nodes"], data["tets"], point_data={"chest_wall": data["chest_wall"],
                                                                "surface": data["surface"]})
    from BreastBiomechLib.mesh.primitives import smooth_hemi_ellipsoid_mesh

    return smooth_hemi_ellipsoid_mesh(BENCH_RADII_MM, edge_mm)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default=None)
    p.add_argument("--batch", type=int, default=1)
    p.add_argument("--edge-mm", type=float, default=1.6077571432,
                   help="the TetGen mesh's size parameter (the default gives 138 609 tets)")
    p.add_argument("--mesh", help="read the mesh from this .npz instead of running TetGen")
    p.add_argument("--save", help="keep the mesh in this .npz")
    p.add_argument("--repeat", type=int, default=2)
    args = p.parse_args()
    mesh = tetgen_breast(args.edge_mm, args.mesh)
    if args.save:
        np.savez_compressed(args.save, nodes=mesh.nodes, tets=mesh.tets, **mesh.point_data)
    model = plate_compression(mesh)  # the bench's loading
    start = time.perf_counter()
    order = ordering.SolverOrder.for_mesh(mesh)
    if order is None:
        raise SystemExit("this mesh is not one the solver renumbers (too small or local already)")
    renumbered = (order.model(model), [order.materials(model.materials)] * args.batch)
    renumbering = time.perf_counter() - start
    floor, ordering.MIN_ELEMENTS = ordering.MIN_ELEMENTS, 10**12  # the own order solved as it is, also on the CPU
    answers = {}
    own = (model, [model.materials] * args.batch)
    for label, (solved, materials) in (("renumbered", renumbered), ("own order", own)):
        solve_batch(solved, materials, device=args.device, relaxation=DynamicRelaxation(max_iterations=1200))  # warm-up
        for _ in range(args.repeat):
            start = time.perf_counter()
            s = solve_batch(solved, materials, device=args.device, relaxation=DynamicRelaxation())[0]
            call = time.perf_counter() - start
            answers[label] = s.displacement
            print(json.dumps({"order": label, "tets": len(mesh.tets), "nodes": len(mesh.nodes), "batch": args.batch,
                              "sectors_per_corner_read": round(ordering.sectors_per_corner_read(solved.mesh.tets), 1),
                              "iterations": s.steps, "solve_s": round(s.wall_time, 4), "call_s": round(call, 4),
                              "us_per_model_step": round(1e6 * s.wall_time / s.steps / args.batch, 2),
                              "status": s.status}), flush=True)
    ordering.MIN_ELEMENTS = floor
    difference = np.abs(order.mesh_values(answers["renumbered"]) - answers["own order"]).max()
    print(json.dumps({"renumbering_s": round(renumbering, 4), "largest nodal difference (mm)": float(difference)}),
          flush=True)


if __name__ == "__main__":
    main()
