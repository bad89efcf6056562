"""What the solver's node kernel could cost (issue 25): its memory traffic alone, streamed.

Every step the node kernel (``kernels.node_kernel``'s ``advance_nodes``) of a batch of B models
reads each node-model's force (three planes of floats), displacement, rounding remainder and
increment (vec3 each) and mass, writes the three vectors back and clears the force: 100 bytes
per node-model (and 4 to clear the node's ANP sum), whatever else it does (contact,
constraints, flags).
This script runs exactly that traffic with the update's arithmetic (a damped central
difference with the compensated sum) and nothing else, in the solver's layout (models
innermost), with fast math as the solver's kernels, replayed as a CUDA graph of ``--launches``
launches (the best of three, ``graph_replay.replayed``); and, for scale, a plain copy of as many
16-byte records. The node kernel's own time is ``benchmarks/solver_profile.py``'s (Nsight
Compute); their ratio is what contact, constraints, the model list and the flags cost on top of
the bytes.

    python benchmarks/node_update_floor.py [--nodes 30296] [--batch 64] [--launches 100] [--device cuda]

prints one JSON line: microseconds per launch and per model, and the bytes' rate (TB/s). The
default node count is ``bench solver``'s 160k-tet hemi-ellipsoid's. Never asserted anywhere.
On the H200 (2026-12-02) this traffic took 52.5 us a launch at 64 models (0.82 us per model,
3.7 TB/s; measured with the same kernel in a probe whose arithmetic differed in its constants),
against the node kernel's 3.2-4.0 us per model-step (docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import warp as wp

from graph_replay import replayed  # this folder's

wp.set_module_options({"fast_math": True})  # as the solver's kernels (solver/kernels/common.py)

UPDATE_BYTES = 3 * 4 + 3 * 12 + 4 + 3 * 12 + 3 * 4  # reads: force planes, u/low/du, mass; writes: u/low/du, force
COPY_BYTES = 2 * 16


@wp.kernel
def node_update(u: wp.array(dtype=wp.vec3), low: wp.array(dtype=wp.vec3), du: wp.array(dtype=wp.vec3),
                forces: wp.array2d(dtype=float), mass: wp.array(dtype=float), dt: float, damping: float):
    """One node-model per thread: du <- ((-f) dt^2 / m + (1 - a dt/2) du) / (1 + a dt/2), u += du
    with the rounding remainder in ``low``; the force cleared (SI units)."""
    i = wp.tid()
    f = wp.vec3(forces[0, i], forces[1, i], forces[2, i])
    x, rest, last, m = u[i], low[i], du[i], mass[i]
    forces[0, i] = 0.0
    forces[1, i] = 0.0
    forces[2, i] = 0.0
    half = 0.5 * damping * dt
    step = (-f / m * (dt * dt) + (1.0 - half) * last) / (1.0 + half)
    y = step + rest
    total = x + y
    low[i] = y - (total - x)
    u[i] = total
    du[i] = step


@wp.kernel
def copy_records(src: wp.array(dtype=wp.vec4), dst: wp.array(dtype=wp.vec4)):
    i = wp.tid()
    dst[i] = src[i]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nodes", type=int, default=30296)
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--launches", type=int, default=100)
    parser.add_argument("--device", default="cuda")
    args = parser.parse_args()
    wp.init()
    device = wp.get_device(args.device)
    if not device.is_cuda:
        raise SystemExit("the node update's floor is a GPU figure: give a CUDA --device")
    n = args.nodes * args.batch
    with wp.ScopedDevice(device):
        state = [wp.zeros(n, dtype=wp.vec3) for _ in range(3)]
        forces = wp.zeros((3, n), dtype=float)
        mass = wp.array(np.full(n, 1e-4, np.float32), dtype=float)
        update = replayed([(node_update, n, state + [forces, mass, 1e-4, 10.0], 256)], repeats=args.launches)
        records = [wp.zeros(n, dtype=wp.vec4), wp.zeros(n, dtype=wp.vec4)]
        copy = replayed([(copy_records, n, records, 256)], repeats=args.launches)
    print(json.dumps({
        "benchmark": "node_update_floor", "device": device.name, "nodes": args.nodes, "batch": args.batch,
        "update_us_per_launch": round(update, 2), "update_us_per_model": round(update / args.batch, 3),
        "update_TB_per_s": round(UPDATE_BYTES * n / update / 1e6, 2),
        "copy_us_per_launch": round(copy, 2), "copy_TB_per_s": round(COPY_BYTES * n / copy / 1e6, 2),
    }))


if __name__ == "__main__":
    main()
