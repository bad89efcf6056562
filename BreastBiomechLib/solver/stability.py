"""Checking the explicit time step against the stiffness of the deformed model.

The automatic step comes from the reference element sizes and wave speeds. As elements deform
and materials stiffen the stable step changes, so during a solve the largest eigenvalue
omega_max^2 of M^-1 K (K the tangent stiffness of the current configuration, by finite
differences of the internal forces) is tracked by power iteration: one iteration per sample,
warm-started from the previous vector. Its Rayleigh quotient never exceeds omega_max^2, so the
central-difference limit 2 / omega_max it implies is an upper bound of the true stable step:
a time step above it is certainly unstable.

Under mass scaling (:class:`MassScaling`) the fictitious masses grow where the step comes too
close to that limit, on the device, so that a relaxation's steps can run ahead of the host.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import warp as wp

from BreastBiomechLib.solver import kernels as k
from BreastBiomechLib.solver.capture import graph_capture
from BreastBiomechLib.solver.packing import Selection
from BreastBiomechLib.solver.readback import HostCopy

SMALLEST_MASS_TERM = 1e-300  # v^T M v below this is taken as this: no division by zero
RESCALE_ABOVE = 0.9  # mass scaling: masses grow once the step is this fraction of the stable one
RESCALE_TO = 0.8  # ... so that it is this fraction


class StableStepMonitor:
    """Power iteration for the stable time step (s) of B models sharing a mesh.

    ``internal_force(state, out)`` writes the internal nodal forces (N) of displacement ``state``
    (m) into ``out`` (component planes of shape (3, B*N), see :mod:`BreastBiomechLib.solver.kernels`);
    ``mass`` holds the lumped nodal masses (kg, B*N); ``probe_m`` is the size of the
    finite-difference probe (m), about 1e-3 of an element."""

    def __init__(self, internal_force: Callable, mass: wp.array, n_models: int, n_nodes: int, probe_m: float,
                 constrained_nodes: wp.array, constrained_mask: wp.array, seed: int = 0):
        self._force = internal_force
        self._mass = mass
        self._B, self._N = n_models, n_nodes
        self._eps = float(probe_m)
        self._cnodes, self._cmask = constrained_nodes, constrained_mask
        start = np.random.default_rng(seed).uniform(-1.0, 1.0, (n_models * n_nodes, 3)).astype(np.float32)
        self._v = wp.array(start, dtype=wp.vec3)
        self._w = wp.zeros_like(self._v)
        self._probe = wp.zeros_like(self._v)
        self._f_base = wp.zeros((3, n_models * n_nodes), dtype=float)  # component planes, see kernels
        self._f_probe = wp.zeros_like(self._f_base)
        self._vkv, self._vmv, self._largest = (wp.zeros(n_models, dtype=float) for _ in range(3))
        self.stable = wp.zeros(n_models, dtype=wp.float64)  # the estimate after the last advance (s)
        self._stable_host = HostCopy(self.stable)
        self._zero_constrained()

    def _zero_constrained(self) -> None:
        n_con = self._cnodes.shape[0]
        if n_con:
            wp.launch(k.zero_constrained, self._B * n_con, [self._v, self._cnodes, self._cmask, self._N, n_con])

    def advance(self, state: wp.array, iterations: int = 1, base_force: wp.array | None = None) -> None:
        """``iterations`` power iterations at displacement ``state`` (m) and the stable step they
        give, for :meth:`stable_step`; device work (no host synchronisation, so it can be captured
        in a graph). ``base_force``: the internal forces of ``state`` when the caller has them."""
        if base_force is None:
            self._force(state, self._f_base)
        f_base = self._f_base if base_force is None else base_force
        device = self._v.device
        if iterations > 1 and device.is_cuda and not device.is_capturing:
            # one iteration captured and replayed: its ten launches cost the host about 20 us
            # each, ten times the device's time, and the GPU would stand idle between them
            with graph_capture(device) as capture:
                self._iterate(state, f_base)
            for _ in range(iterations):
                wp.capture_launch(capture.graph)
        else:
            for _ in range(iterations):
                self._iterate(state, f_base)
        wp.launch(k.stable_steps, self._B, [self._vkv, self._vmv, SMALLEST_MASS_TERM, self.stable])
        self._stable_host.refresh()

    def _iterate(self, state: wp.array, f_base: wp.array) -> None:
        """One power iteration: the next iterate and the Rayleigh quotient terms of this one."""
        wp.launch(k.perturbed, self._B * self._N, [state, self._v, self._eps, self._probe])
        self._force(self._probe, self._f_probe)
        for a in (self._vkv, self._vmv, self._largest):
            a.zero_()
        k.reduction_launch(k.power_iteration_terms, self._B, self._N,
                           [self._v, self._f_probe, f_base, self._mass, self._eps, self._N, self._vkv, self._vmv,
                            self._w, self._largest])
        wp.launch(k.normalise_iterate, self._B * self._N, [self._w, self._largest, self._N, self._v])
        self._zero_constrained()

    def keep(self, models: Selection, mass: wp.array) -> None:
        """Go on with the selected models of the batch only (see
        :mod:`~BreastBiomechLib.solver.packing`), whose masses are now ``mass``; device work."""
        for name in ("_v", "_w", "_probe", "_f_base", "_f_probe", "_vkv", "_vmv", "_largest", "stable"):
            setattr(self, name, models.take(getattr(self, name)))
        self._B, self._mass = len(models), mass
        self._stable_host.follow(self.stable)

    def stable_step(self, after: wp.Event | None = None) -> np.ndarray:
        """The stable step estimate 2 / omega (s) per model after the last :meth:`advance` (inf
        where no stiffness was seen); ``after``: an event recorded after that advance (see
        :meth:`HostCopy.read`)."""
        return self._stable_host.read(after)


class MassScaling:
    """Fictitious masses (kg, float32 ``mass`` as the steps read it, node a of model b at a*B + b)
    kept heavy enough that the time step ``dt`` (s) stays stable as elements stiffen: where some
    model's step exceeds :data:`RESCALE_ABOVE` of its stable step (:class:`StableStepMonitor`;
    frozen models - an inverted element, or converged - left out), every model whose step exceeds
    :data:`RESCALE_TO` of its stable step has its masses multiplied by (dt / (RESCALE_TO x
    stable))^2, which brings the step to that fraction; the static solution does not depend on
    them. Device work (capturable in a graph); the masses are held in float64 too, so that
    repeated growth rounds once. After
    :meth:`apply`: :attr:`stable` the stable step of the scaled masses (s), :attr:`growth` each
    model's total growth, :attr:`rescales` how often its masses grew."""

    def __init__(self, mass: wp.array, mass_float64: np.ndarray, dt: float, n_models: int) -> None:
        self.mass = mass
        self.mass_float64 = wp.array(mass_float64, dtype=wp.float64, device=mass.device)
        self.dt = float(dt)
        self.stable = wp.zeros(n_models, dtype=wp.float64, device=mass.device)
        self.growth = wp.array(np.ones(n_models), dtype=wp.float64, device=mass.device)
        self.rescales = wp.zeros(n_models, dtype=int, device=mass.device)
        self._grow = wp.zeros(n_models, dtype=wp.float64, device=mass.device)

    def apply(self, monitor: StableStepMonitor, inverted: wp.array) -> None:
        """Grow the masses as the monitor's last estimate needs; ``inverted``: the solver's flags
        (4 per model, the count first)."""
        n_models = self.stable.shape[0]
        wp.launch(k.keep_step_stable, n_models, [monitor.stable, inverted, self.dt, RESCALE_ABOVE, RESCALE_TO,
                                                 self.stable, self._grow, self.growth, self.rescales])
        wp.launch(k.grow_masses, self.mass.shape[0], [self._grow, self.mass_float64, self.mass])

    def keep(self, models: Selection, mass: wp.array) -> None:
        """Go on with the selected models of the batch only (see
        :mod:`~BreastBiomechLib.solver.packing`), whose float32 masses are now ``mass``; device work."""
        for name in ("mass_float64", "stable", "growth", "rescales", "_grow"):
            setattr(self, name, models.take(getattr(self, name)))
        self.mass = mass
