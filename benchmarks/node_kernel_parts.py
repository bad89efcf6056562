"""What each part of the solver's node kernel costs (issue 25): ``advance_nodes`` replayed alone,
against copies of it built with parts left out, added one at a time, or arranged otherwise.

The node kernel (``kernels.node_kernel``'s ``advance_nodes``) takes a third of a batch's step, and
some four times the time of its bytes streamed alone (``node_update_floor.py``). This script
records the solver's own launch of it (every model listed) from a short relaxation of ``bench
solver``'s hemi-ellipsoid, then replays, each alone in a CUDA graph of 20 launches
(``graph_replay.replayed``, µs per launch), the solver's kernel and a copy of it whose parts are
compile-time switches:

- ``plates``: contact with the plates (each node's slot per plate read, then the pose);
- ``constraints``: the node's prescribed components (its row read with the node's reads);
- ``anp_clear``: the ANP sums cleared, a thread's entries before its node's reads;
- ``flags``: the model's inversion count and frozen flag, and the early return they decide;
- ``model_scalars``: the model's damping and load time (else constants);
- ``cap``: the solver's register cap (``kernels.NODE_KERNEL_OPTIONS``).

Variants: ``copy`` (every part), ``without_<part>``, ``update_only`` (no part: the floor
script's work in the solver's layout, model list and launch), ``update_plus_<part>``, and
``slots_first`` (the plate slots read with the node's other reads, as two scalars, the two
plates' contact unrolled). The copy is straight-line code as the solver's: wrapped in a loop over
a thread's nodes (even of one node) the same update took 279 µs a launch against the solver's
172 at 64 models (H200), so the loop, not the parts, would have been measured.
Before timing, every variant that keeps every part is run once from the recorded state beside
the solver's kernel and must leave its displacements, increments, forces and ANP sums (see
:func:`check`), so the copy cannot drift from the solver unnoticed; on the CPU (``--device
cpu``) the script does only that check, to the last bit.

    python benchmarks/node_kernel_parts.py [--tets 160000] [--batch 64] [--device cuda] [--variants NAME ...]

prints one JSON line: the node count, the contact slots, and µs per launch by variant. Never
asserted anywhere. Figures: docs/benchmarks.md (H200, 2026-12-02, sixth and seventh sessions).

What a variant's figure does and does not say: it times the copy's build, and ptxas schedules
this kernel differently for small differences of source or arguments (one source with and
without the register cap, 48 registers both: 175 and 198 µs; the copy as committed 190 against
175 in its working version), so read a variant against ``copy``, not against ``solver``. A
change that a copy runs faster must be built into the solver and timed as the solver's kernel
(``solver`` here, run with the changed library) and in the solve (``compare_libraries.py``)
before it is believed: the special-node rows ran 22 % faster than the solver's kernel as a
probe's copy, 3-10 % faster (or 22 % slower, with the cap) as the solver's build, and in the
solve a batch of 64 0.8-3.4 % faster while a lone model and 2M tets were 1-4 % slower (seventh
session). The solver's own kernel replayed alone does match its time in the solve (Nsight
Compute, within 3 %).
"""

from __future__ import annotations

import argparse
import functools
import json

import numpy as np
import warp as wp

from BreastBiomechLib.cli.bench import _hemi_ellipsoid_spacing, bench_parameter_sets
from BreastBiomechLib.solver import DynamicRelaxation, solve_batch
from BreastBiomechLib.solver import kernels as k
from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression
from graph_replay import argument, recorded_launches, replayed  # this folder's

PARTS = ("plates", "constraints", "anp_clear", "flags", "model_scalars")
VARIANTS = {"copy": {}, "uncapped": {"cap": False}, "slots_first": {"slots_first": True},
            **{f"without_{p}": {p: False} for p in PARTS},
            "update_only": {p: False for p in PARTS},
            **{f"update_plus_{p}": {q: q == p for q in PARTS} for p in PARTS}}
STATE = (0, 1, 2, 3, 4)  # the launch's u, low, du, forces, anp_sums: what a variant must leave as the solver's


@functools.cache
def node_variant(plates: bool = True, constraints: bool = True, anp_clear: bool = True, flags: bool = True,
                 model_scalars: bool = True, cap: bool = True, slots_first: bool = False):
    """``advance_nodes`` (frictionless plates, no gravity or sliding: the bench's loading) with the
    parts switched as named."""
    options = dict(k.NODE_KERNEL_OPTIONS) if cap else {}
    name = "node_parts_" + "".join(str(int(v)) for v in (plates, constraints, anp_clear, flags, model_scalars, cap,
                                                         slots_first))

    @wp.kernel(name=name, module="unique", module_options={"fast_math": True}, **options)
    def advance(u: wp.array(dtype=wp.vec3), low: wp.array(dtype=wp.vec3), du: wp.array(dtype=wp.vec3),
                forces: wp.array2d(dtype=float), anp_sums: wp.array(dtype=float),
                loads: k.NodeLoads, constraints_: k.NodeConstraints, contact: k.PlateContact,
                models: wp.array(dtype=int), n_listed: int, n_models: int, clock: wp.array(dtype=int),
                inverted: wp.array(dtype=int)):
        tid = wp.tid()
        n_nodes = contact.slot.shape[0]
        if wp.static(anp_clear):
            j = tid
            while j < anp_sums.shape[0]:
                anp_sums[j] = 0.0
                j += n_listed * n_nodes
        step = clock[1]
        at = k.listed(models, n_listed, n_models, tid)
        a, b = at[0], at[1]
        if a < 0 or a >= n_nodes:
            return
        count = int(0)
        frozen = int(0)
        if wp.static(flags):
            count = inverted[4 * b]
            frozen = inverted[4 * b + 3]
        damping = float(10.0)
        t_total = float(1.0)
        if wp.static(model_scalars):
            damping = loads.damping[b]
            t_total = loads.t_total[b]
        i = a * n_models + b
        f = k.force_at(forces, i)
        x = k.NodeState()
        x.u = u[i]
        x.low = low[i]
        du_last = du[i]
        mass = loads.mass[i]
        external = wp.vec3(0.0)  # no gravity (see recorded_launch)
        row = int(-1)
        if wp.static(constraints):
            row = constraints_.constrained[a]
        first = int(-1)
        second = int(-1)
        if wp.static(slots_first):
            first = contact.slot[a, 0]
            second = contact.slot[a, 1]
        forces[0, i] = 0.0
        forces[1, i] = 0.0
        forces[2, i] = 0.0
        if tid == 0:
            clock[0] = step + 1
        if count != 0 or frozen != 0:
            if a == 0 and count != 0:
                inverted[4 * b + 3] = 1
            du[i] = wp.vec3(0.0)
            return
        t = float(step + 1) * loads.dt
        s = k.load_factor(t, t_total, loads.load_shape)
        half = 0.5 * damping * loads.dt
        x.du = ((external - f) / mass * (loads.dt * loads.dt) + (1.0 - half) * du_last) / (1.0 + half)
        y = x.du + x.low
        total = x.u + y
        x.low = y - (total - x.u)
        x.u = total
        if row >= 0:
            mask = constraints_.mask[row]
            shape = constraints_.shapes[row]
            v = constraints_.value[row * n_models + b]
            target = k.load_factor(t, t_total, shape[0]) * v
            if shape[1] != shape[0] or shape[2] != shape[0]:
                target = wp.vec3(target[0], k.load_factor(t, t_total, shape[1]) * v[1],
                                 k.load_factor(t, t_total, shape[2]) * v[2])
            previous = x.u - x.du
            x.u = k.set_component(x.u, mask, target)
            x.du = k.set_component(x.du, mask, target - previous)
            x.low = k.set_component(x.low, mask, wp.vec3(0.0))
        if wp.static(plates):
            if wp.static(slots_first):  # the bench's two plates, unrolled
                if first >= 0:
                    x = k.touch_plate(x, a, b * 2, first * n_models + b, s, f - external, contact, 0)
                if second >= 0:
                    x = k.touch_plate(x, a, b * 2 + 1, second * n_models + b, s, f - external, contact, 0)
            else:
                for p in range(contact.n_plates):
                    slot = contact.slot[a, p]
                    if slot >= 0:
                        x = k.touch_plate(x, a, b * contact.n_plates + p, slot * n_models + b, s, f - external,
                                          contact, 0)
        u[i] = x.u
        du[i] = x.du
        low[i] = x.low

    return advance


def recorded_launch(tets: int, batch: int, device: str) -> tuple:
    """The solver's first ``advance_nodes`` launch with all ``batch`` models listed, in a short
    relaxation of the bench's model: (kernel, threads, inputs, block)."""
    model = hemi_ellipsoid_compression(_hemi_ellipsoid_spacing(tets), compression=0.25)
    with recorded_launches() as launches:
        solve_batch(model, bench_parameter_sets(model.materials, batch), device=device,
                    relaxation=DynamicRelaxation(load_iterations=200, max_iterations=400))
    record = next(r for r in launches if r[0].func.__name__ == "advance_nodes" and argument(r, "n_listed") == batch)
    kernel, dim, inputs, block = record
    plates, constraints = argument(record, "plates"), argument(record, "constraints")
    if plates.n_plates != 2 or constraints.n_sliding or kernel is not k.node_kernel(False, False, False):
        raise SystemExit("the bench's loading changed (its node kernel is not the frictionless one without gravity "
                         "or sliding, or it has not two plates): this script's copy no longer applies")
    argument(record, "inverted").zero_()  # every model moves again
    return kernel, dim, inputs, block


def check(kernel, dim: int, inputs: list, block: int, names: list, exact: bool) -> None:
    """Each complete variant, run once from the recorded state, leaves the solver kernel's state:
    to the last bit (``exact``, the CPU), or on a GPU, where the compiler may fuse a product and a
    sum in one build and not in the other, the displacements, increments, forces and ANP sums
    within 1e-5 of each one's largest value (the last increment's term scaled by 1 + 1e-4 fails
    it; the remainders are left out, as they are the rounding of the displacements): the CPU's
    check is the exact one. The state is put back after each."""
    saved = [inputs[n].numpy().copy() for n in STATE]

    def run(launched):
        for n, values in zip(STATE, saved):
            inputs[n].assign(values)
        wp.launch(launched, dim, inputs, block_dim=block)
        return [inputs[n].numpy().astype(np.float64) for n in STATE]

    def agree(expected, got, n):
        if exact:
            return np.array_equal(expected, got)
        return n == 1 or np.abs(expected - got).max() <= 1e-5 * max(np.abs(expected).max(), 1e-30)

    expected = run(kernel)
    for name in names:
        if any(VARIANTS[name].get(p, True) is False for p in PARTS):
            continue  # a variant without a part does other work by design
        got = run(node_variant(**VARIANTS[name]))
        if not all(agree(e, g, n) for n, e, g in zip(STATE, expected, got)):
            raise SystemExit(f"{name}: not the solver's node update ({'to the last bit' if exact else 'within 1e-5'}); "
                             "mend the copy in this script")
    for n, values in zip(STATE, saved):
        inputs[n].assign(values)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tets", type=int, default=160_000, help="about this many tets (the bench's mesh)")
    parser.add_argument("--batch", type=int, default=64, help="models solved together (2 at least)")
    parser.add_argument("--device", default="cuda", help="a CUDA device times; the CPU only checks the copies")
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    args = parser.parse_args()
    if args.batch < 2:
        parser.error("--batch must be 2 or more (a lone model's node kernel takes no model list)")
    wp.init()
    kernel, dim, inputs, block = recorded_launch(args.tets, args.batch, args.device)
    slots = argument((kernel, dim, inputs, block), "plates").slot.numpy()
    figures = {"benchmark": "node_kernel_parts", "device": wp.get_device(args.device).name, "batch": args.batch,
               "nodes": dim // args.batch, "contact_slots": int(np.count_nonzero(slots >= 0))}
    with wp.ScopedDevice(args.device):
        check(kernel, dim, inputs, block, args.variants, exact=not wp.get_device(args.device).is_cuda)
        if wp.get_device(args.device).is_cuda:
            figures["solver"] = round(replayed([(kernel, dim, inputs, block)]), 2)
            for name in args.variants:
                launch = (node_variant(**VARIANTS[name]), dim, inputs, block)
                figures[name] = round(replayed([launch]), 2)
            figures["solver_again"] = round(replayed([(kernel, dim, inputs, block)]), 2)
        else:
            figures["checked"] = [n for n in args.variants if all(VARIANTS[n].get(p, True) for p in PARTS)]
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
