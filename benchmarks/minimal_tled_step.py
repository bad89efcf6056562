"""The reference the solver's step is measured against (issue 25): a minimal warp TLED step.

One neo-Hookean four-node-tet element kernel (no ANP, no visco, no fibres, no inversion
flags: F, its stress and four atomic adds) and one node kernel (undamped central difference,
no constraints, no contact); with ``--anp`` also the average-nodal-pressure pass (one slot per
node) before it; with ``--gather`` the element kernel stores its four nodal forces and the
node kernel sums them through a node-to-entries index (no atomics, as NiftySim assembles); with
``--planes`` the nodal forces are three planes of floats, one per component, as the solver's
(``kernels.add_force``), instead of a vec3 array; replayed as CUDA graphs of ``--graph-steps``
steps (default 10, as the solver replays its steps) on the benchmarks' hemi-ellipsoid
(``breastbiomech bench solver``'s mesh at the same ``--tets``). The solver's step does more
(ANP's second element pass, damping, constraints, plates, per-model flags), so the ratio of the
two per-step times is the price of that work plus whatever the solver wastes.

    python benchmarks/minimal_tled_step.py --tets 160000 [--steps 4000] [--device cuda] [--anp | --gather] [--planes]
                                           [--graph-steps 10]

prints one JSON line: the mesh size, microseconds per step and per element-step. Units inside
the kernels are SI (m, Pa, kg, s, N). Times are wall-clock over synchronised graph replays,
after a warm-up; never asserted anywhere.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import warp as wp

from BreastBiomechLib.cli.bench import BENCH_RADII_MM, _hemi_ellipsoid_spacing
from BreastBiomechLib.mesh.primitives import hemi_ellipsoid_mesh
from BreastBiomechLib.solver.geometry import shape_derivatives
from BreastBiomechLib.solver.settings import MM


@wp.func
def deformation_gradient(u: wp.array(dtype=wp.vec3), n0: int, n1: int, n2: int, n3: int,
                         d0: wp.vec3, d1: wp.vec3, d2: wp.vec3, d3: wp.vec3) -> wp.mat33:
    """F = I + sum_a u_a (x) dN_a/dX."""
    return (wp.identity(n=3, dtype=float) + wp.outer(u[n0], d0) + wp.outer(u[n1], d1) + wp.outer(u[n2], d2)
            + wp.outer(u[n3], d3))


@wp.func
def first_piola_kirchhoff(F: wp.mat33, mu: float, kappa: float) -> wp.mat33:
    """F S of a compressible neo-Hookean solid, W = mu/2 (I1bar - 3) + kappa/2 (J - 1)^2 (Pa)."""
    C = wp.transpose(F) * F
    Cinv = wp.inverse(C)
    J = wp.determinant(F)
    S = (mu * wp.pow(J, -2.0 / 3.0) * (wp.identity(n=3, dtype=float) - ((C[0, 0] + C[1, 1] + C[2, 2]) / 3.0) * Cinv)
         + kappa * J * (J - 1.0) * Cinv)
    return F * S


@wp.func
def scatter(forces: wp.array(dtype=wp.vec3), n0: int, n1: int, n2: int, n3: int, P: wp.mat33,
            d0: wp.vec3, d1: wp.vec3, d2: wp.vec3, d3: wp.vec3):
    """f_a += P dN_a/dX at the element's four nodes (atomic adds)."""
    wp.atomic_add(forces, n0, P * d0)
    wp.atomic_add(forces, n1, P * d1)
    wp.atomic_add(forces, n2, P * d2)
    wp.atomic_add(forces, n3, P * d3)


@wp.kernel
def element_forces(u: wp.array(dtype=wp.vec3), tets: wp.array2d(dtype=int), dhdx: wp.array2d(dtype=wp.vec3),
                   vol: wp.array(dtype=float), mu: float, kappa: float, forces: wp.array(dtype=wp.vec3)):
    """f_a += V0 F S dN_a/dX for a compressible neo-Hookean solid (W = mu/2 (I1bar - 3) + kappa/2 (J - 1)^2)."""
    e = wp.tid()
    n0, n1, n2, n3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
    d0, d1, d2, d3 = dhdx[e, 0], dhdx[e, 1], dhdx[e, 2], dhdx[e, 3]
    F = deformation_gradient(u, n0, n1, n2, n3, d0, d1, d2, d3)
    P = vol[e] * first_piola_kirchhoff(F, mu, kappa)
    scatter(forces, n0, n1, n2, n3, P, d0, d1, d2, d3)


@wp.kernel
def nodal_pressure(u: wp.array(dtype=wp.vec3), tets: wp.array2d(dtype=int), dhdx: wp.array2d(dtype=wp.vec3),
                   vol: wp.array(dtype=float), kappa: float, pressure_volume: wp.array(dtype=float)):
    """ANP pass 1 (``--anp``): kappa (J - 1) V at each node of the element, one slot per node."""
    e = wp.tid()
    n0, n1, n2, n3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
    F = deformation_gradient(u, n0, n1, n2, n3, dhdx[e, 0], dhdx[e, 1], dhdx[e, 2], dhdx[e, 3])
    pv = kappa * (wp.determinant(F) - 1.0) * vol[e]
    wp.atomic_add(pressure_volume, n0, pv)
    wp.atomic_add(pressure_volume, n1, pv)
    wp.atomic_add(pressure_volume, n2, pv)
    wp.atomic_add(pressure_volume, n3, pv)


@wp.func
def anp_scaled(F: wp.mat33, n0: int, n1: int, n2: int, n3: int, kappa: float,
               pressure_volume: wp.array(dtype=float), node_volume: wp.array(dtype=float)) -> wp.mat33:
    """F scaled to the mean of the element's nodes' averaged J (``--anp``, one slot per node)."""
    pm = 0.25 * (pressure_volume[n0] / node_volume[n0] + pressure_volume[n1] / node_volume[n1]
                 + pressure_volume[n2] / node_volume[n2] + pressure_volume[n3] / node_volume[n3])
    return wp.pow((pm / kappa + 1.0) / wp.determinant(F), 1.0 / 3.0) * F


@wp.kernel
def anp_element_forces(u: wp.array(dtype=wp.vec3), tets: wp.array2d(dtype=int), dhdx: wp.array2d(dtype=wp.vec3),
                       vol: wp.array(dtype=float), mu: float, kappa: float, pressure_volume: wp.array(dtype=float),
                       node_volume: wp.array(dtype=float), forces: wp.array(dtype=wp.vec3)):
    """``--anp``: the element's F scaled to the mean of its nodes' averaged J, then as :func:`element_forces`."""
    e = wp.tid()
    n0, n1, n2, n3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
    d0, d1, d2, d3 = dhdx[e, 0], dhdx[e, 1], dhdx[e, 2], dhdx[e, 3]
    F = deformation_gradient(u, n0, n1, n2, n3, d0, d1, d2, d3)
    F = anp_scaled(F, n0, n1, n2, n3, kappa, pressure_volume, node_volume)
    P = vol[e] * first_piola_kirchhoff(F, mu, kappa)
    scatter(forces, n0, n1, n2, n3, P, d0, d1, d2, d3)


@wp.func
def scatter_planes(forces: wp.array2d(dtype=float), n0: int, n1: int, n2: int, n3: int, P: wp.mat33,
                   d0: wp.vec3, d1: wp.vec3, d2: wp.vec3, d3: wp.vec3):
    """``--planes``: as :func:`scatter`, into forces[c, node], one plane per component."""
    for c in range(3):
        wp.atomic_add(forces, c, n0, (P * d0)[c])
        wp.atomic_add(forces, c, n1, (P * d1)[c])
        wp.atomic_add(forces, c, n2, (P * d2)[c])
        wp.atomic_add(forces, c, n3, (P * d3)[c])


@wp.kernel
def element_forces_planes(u: wp.array(dtype=wp.vec3), tets: wp.array2d(dtype=int), dhdx: wp.array2d(dtype=wp.vec3),
                          vol: wp.array(dtype=float), mu: float, kappa: float, forces: wp.array2d(dtype=float)):
    """``--planes``: :func:`element_forces` scattering into component planes."""
    e = wp.tid()
    n0, n1, n2, n3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
    d0, d1, d2, d3 = dhdx[e, 0], dhdx[e, 1], dhdx[e, 2], dhdx[e, 3]
    F = deformation_gradient(u, n0, n1, n2, n3, d0, d1, d2, d3)
    P = vol[e] * first_piola_kirchhoff(F, mu, kappa)
    scatter_planes(forces, n0, n1, n2, n3, P, d0, d1, d2, d3)


@wp.kernel
def anp_element_forces_planes(u: wp.array(dtype=wp.vec3), tets: wp.array2d(dtype=int),
                              dhdx: wp.array2d(dtype=wp.vec3), vol: wp.array(dtype=float), mu: float, kappa: float,
                              pressure_volume: wp.array(dtype=float), node_volume: wp.array(dtype=float),
                              forces: wp.array2d(dtype=float)):
    """``--anp --planes``: :func:`anp_element_forces` scattering into component planes."""
    e = wp.tid()
    n0, n1, n2, n3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
    d0, d1, d2, d3 = dhdx[e, 0], dhdx[e, 1], dhdx[e, 2], dhdx[e, 3]
    F = deformation_gradient(u, n0, n1, n2, n3, d0, d1, d2, d3)
    F = anp_scaled(F, n0, n1, n2, n3, kappa, pressure_volume, node_volume)
    P = vol[e] * first_piola_kirchhoff(F, mu, kappa)
    scatter_planes(forces, n0, n1, n2, n3, P, d0, d1, d2, d3)


@wp.kernel
def element_forces_stored(u: wp.array(dtype=wp.vec3), tets: wp.array2d(dtype=int), dhdx: wp.array2d(dtype=wp.vec3),
                          vol: wp.array(dtype=float), mu: float, kappa: float,
                          element_node_forces: wp.array2d(dtype=wp.vec3)):
    """``--gather``: as :func:`element_forces`, each element's four nodal forces stored, not scattered."""
    e = wp.tid()
    n0, n1, n2, n3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
    d0, d1, d2, d3 = dhdx[e, 0], dhdx[e, 1], dhdx[e, 2], dhdx[e, 3]
    F = deformation_gradient(u, n0, n1, n2, n3, d0, d1, d2, d3)
    P = vol[e] * first_piola_kirchhoff(F, mu, kappa)
    element_node_forces[e, 0] = P * d0
    element_node_forces[e, 1] = P * d1
    element_node_forces[e, 2] = P * d2
    element_node_forces[e, 3] = P * d3


@wp.kernel
def gathered_central_difference(u: wp.array(dtype=wp.vec3), u_prev: wp.array(dtype=wp.vec3),
                                element_node_forces: wp.array(dtype=wp.vec3), start: wp.array(dtype=int),
                                entries: wp.array(dtype=int), external: wp.array(dtype=wp.vec3),
                                mass: wp.array(dtype=float), dt: float):
    """``--gather``: the node's force summed from its elements' stored forces (``entries[start[i]:
    start[i+1]]`` index the flattened (M, 4) array), then as :func:`central_difference`."""
    i = wp.tid()
    f = wp.vec3(0.0)
    for k in range(start[i], start[i + 1]):
        f = f + element_node_forces[entries[k]]
    un = u[i]
    u[i] = 2.0 * un - u_prev[i] + (external[i] - f) * (dt * dt / mass[i])
    u_prev[i] = un


@wp.kernel
def central_difference(u: wp.array(dtype=wp.vec3), u_prev: wp.array(dtype=wp.vec3), forces: wp.array(dtype=wp.vec3),
                       external: wp.array(dtype=wp.vec3), mass: wp.array(dtype=float), dt: float,
                       pressure_volume: wp.array(dtype=float)):
    """u_(n+1) = 2 u_n - u_(n-1) + (R - F) dt^2 / m; the forces (and ANP pressures) cleared for the next step."""
    i = wp.tid()
    un = u[i]
    u[i] = 2.0 * un - u_prev[i] + (external[i] - forces[i]) * (dt * dt / mass[i])
    u_prev[i] = un
    forces[i] = wp.vec3(0.0)
    if i < pressure_volume.shape[0]:
        pressure_volume[i] = 0.0


@wp.kernel
def central_difference_planes(u: wp.array(dtype=wp.vec3), u_prev: wp.array(dtype=wp.vec3),
                              forces: wp.array2d(dtype=float), external: wp.array(dtype=wp.vec3),
                              mass: wp.array(dtype=float), dt: float, pressure_volume: wp.array(dtype=float)):
    """``--planes``: :func:`central_difference` with the forces read from (and cleared in) their planes."""
    i = wp.tid()
    un = u[i]
    f = wp.vec3(forces[0, i], forces[1, i], forces[2, i])
    u[i] = 2.0 * un - u_prev[i] + (external[i] - f) * (dt * dt / mass[i])
    u_prev[i] = un
    for c in range(3):
        forces[c, i] = 0.0
    if i < pressure_volume.shape[0]:
        pressure_volume[i] = 0.0


def measure(tets_wanted: int, steps: int, device: str | None, anp: bool = False, gather: bool = False,
            planes: bool = False, graph_size: int = 10) -> dict:
    """The minimal step's figures (see the module docstring); ``graph_size`` steps per CUDA graph."""
    wp.init()
    dev = wp.get_device(device)
    mesh = hemi_ellipsoid_mesh(BENCH_RADII_MM, _hemi_ellipsoid_spacing(tets_wanted))
    nodes = mesh.nodes * MM
    dhdx, vol = shape_derivatives(nodes, mesh.tets)
    n, m = len(nodes), len(mesh.tets)
    E, nu, rho = 10e3, 0.49, 1000.0
    mu, kappa = E / (2 * (1 + nu)), E / (3 * (1 - 2 * nu))
    mass = np.bincount(mesh.tets.ravel(), weights=np.repeat(rho * vol / 4, 4), minlength=n)
    dt = 1e-7  # small enough for any mesh here; the time per step does not depend on it
    with wp.ScopedDevice(dev):
        d_tets = wp.array(mesh.tets.astype(np.int32), dtype=int)
        d_dhdx = wp.array(dhdx.astype(np.float32), dtype=wp.vec3)
        d_vol = wp.array(vol.astype(np.float32), dtype=float)
        d_mass = wp.array(mass.astype(np.float32), dtype=float)
        u = wp.zeros(n, dtype=wp.vec3)
        u_prev = wp.zeros(n, dtype=wp.vec3)
        forces = wp.zeros((3, n), dtype=float) if planes else wp.zeros(n, dtype=wp.vec3)
        external = wp.array(np.tile([0.0, 0.0, -9.81], (n, 1)) * mass[:, None], dtype=wp.vec3)
        pressure_volume = wp.zeros(n if anp else 0, dtype=float)
        node_volume = wp.array(np.bincount(mesh.tets.ravel(), weights=np.repeat(vol, 4), minlength=n).astype(np.float32),
                               dtype=float)

        order = np.argsort(mesh.tets.ravel(), kind="stable")  # element-node entries grouped by node
        d_entries = wp.array(order.astype(np.int32), dtype=int)
        d_start = wp.array(np.concatenate([[0], np.cumsum(np.bincount(mesh.tets.ravel(), minlength=n))]).astype(np.int32),
                           dtype=int)
        stored = wp.zeros((m, 4), dtype=wp.vec3)

        def two_steps():
            for _ in range(2):
                if gather:
                    wp.launch(element_forces_stored, m, [u, d_tets, d_dhdx, d_vol, mu, kappa, stored])
                    wp.launch(gathered_central_difference, n, [u, u_prev, stored.flatten(), d_start, d_entries,
                                                               external, d_mass, dt])
                    continue
                if anp:
                    wp.launch(nodal_pressure, m, [u, d_tets, d_dhdx, d_vol, kappa, pressure_volume])
                    wp.launch(anp_element_forces_planes if planes else anp_element_forces, m,
                              [u, d_tets, d_dhdx, d_vol, mu, kappa, pressure_volume, node_volume, forces])
                else:
                    wp.launch(element_forces_planes if planes else element_forces, m,
                              [u, d_tets, d_dhdx, d_vol, mu, kappa, forces])
                wp.launch(central_difference_planes if planes else central_difference, n,
                          [u, u_prev, forces, external, d_mass, dt, pressure_volume])

        def graph_steps():
            for _ in range(graph_size // 2):
                two_steps()

        graph_steps()  # compile and warm up
        graph = None
        if dev.is_cuda:
            with wp.ScopedCapture() as capture:
                graph_steps()
            graph = capture.graph
        for _ in range(max(1, 100 // graph_size)):  # warm the clocks and caches
            wp.capture_launch(graph) if graph is not None else graph_steps()
        wp.synchronize_device(dev)
        started = time.perf_counter()
        for _ in range(steps // graph_size):
            wp.capture_launch(graph) if graph is not None else graph_steps()
        wp.synchronize_device(dev)
        wall = time.perf_counter() - started
    done = graph_size * (steps // graph_size)
    return {"benchmark": "minimal_tled_step", "device": str(dev), "device_name": getattr(dev, "name", ""),
            "anp": anp, "gather": gather, "planes": planes, "graph_steps": graph_size, "nodes": n, "tets": m,
            "steps": done, "wall_s": round(wall, 4),
            "us_per_step": round(1e6 * wall / done, 3), "ns_per_element_step": round(1e9 * wall / done / m, 4)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tets", type=int, default=160_000, help="about this many tets (the bench's mesh)")
    parser.add_argument("--steps", type=int, default=4000, help="steps timed")
    parser.add_argument("--device", default=None, help="warp device (cuda, cpu); default warp's")
    parser.add_argument("--anp", action="store_true",
                        help="with average nodal pressure (one more element pass, as the solver's T4ANP)")
    parser.add_argument("--gather", action="store_true",
                        help="element forces stored per element node and gathered per node (no atomics; no ANP)")
    parser.add_argument("--planes", action="store_true",
                        help="nodal forces as three planes of floats (the solver's layout) instead of a vec3 array")
    parser.add_argument("--graph-steps", type=int, default=10,
                        help="steps per CUDA graph, even (default 10: the solver's graphs; 2 until 2026-11-29)")
    args = parser.parse_args()
    if args.gather and args.anp:
        parser.error("--gather is measured without ANP")
    if args.gather and args.planes:
        parser.error("--gather stores its forces per element; --planes is for the atomic scatter")
    if args.graph_steps < 2 or args.graph_steps % 2 or args.steps < args.graph_steps:
        parser.error("--graph-steps is an even number of steps, at least 2 and at most --steps")
    print(json.dumps(measure(args.tets, args.steps, args.device, args.anp, args.gather, args.planes,
                             args.graph_steps)))


if __name__ == "__main__":
    main()
