"""Dynamic relaxation's decisions at each sample, made on the device.

At every sample (every ``update_every`` steps) a relaxation estimates each model's distance to rest
(:class:`DistanceToRest`), sets its damping from Rayleigh quotients and stops the models that have
converged (the rules: :class:`BreastBiomechLib.solver.settings.DynamicRelaxation`). Made on the host,
these decisions kept the GPU idle between a sample and the next steps (10-20 ms of a lone
160k-tet solve on an H200, docs/benchmarks.md); made by :func:`relaxation_update`, one thread
per model in the sample's graph, they let the host enqueue the next steps before it reads the
sample. A converged model is frozen where the steps already freeze a model with an inverted
element (``inverted[4b + 3]``, 2 for converged), so steps enqueued before the host knows of the
stop leave it at rest. The arithmetic is the host's, in float64, operation for operation: the
answers are the same to the last bit (CPU, the developer machine, 2026-11-29).

Units: distances in mm, times in s, eigenvalues (Rayleigh quotients of M^-1 K) in 1/s^2,
damping in 1/s, energies in J.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from BreastBiomechLib.solver import kernels as k
from BreastBiomechLib.solver.packing import Selection
from BreastBiomechLib.solver.readback import HostCopy
from BreastBiomechLib.solver.settings import MM

ROUND_OFF_MM = 2e-5  # float32 round-off of displacements up to ~200 mm
QUOTIENT_WINDOW = 5  # the Rayleigh quotient's reference state is renewed every this many updates
CHATTER_QUOTIENT = 10.0  # a stalled motion whose quotient is this far above the least is chatter
CHATTER_UPDATES = 2  # ... and has stalled at this many updates in a row
SETTLING_UPDATES = 3  # updates after a cold load whose damping follows the latest quotient
SURGE = 10.0  # kinetic energy grown this many times since the previous update: a new transient
MOVING = 1e-6  # ... and at least this fraction of the internal energy
SLOWING = 0.05  # a contraction ratio this much above the previous one: a slower motion is taking over
DAMPING_LIMIT = 1.9  # the damping never exceeds this over the time step (the scheme's stability)
SMALLEST_INERTIA = 1e-300  # a Rayleigh quotient's denominator below this is taken as this


@wp.struct
class DistanceState:
    """:class:`DistanceToRest` on the device, per model b: ``largest[b]`` the largest nodal change
    (m) over the last sampling interval, ``change`` the previous estimate's change (mm), ``rate``
    its contraction ratio, ``slowing`` whether the ratio rose by more than ``slowing_ratio``,
    ``calls`` the estimates made; ``mm`` metres per mm, ``round_off_mm`` the change counted as rest."""
    largest: wp.array(dtype=float)
    change: wp.array(dtype=wp.float64)
    rate: wp.array(dtype=wp.float64)
    slowing: wp.array(dtype=int)
    calls: wp.array(dtype=int)
    mm: wp.float64
    round_off_mm: wp.float64
    slowing_ratio: wp.float64


@wp.func
def estimate_distance(d: DistanceState, b: int) -> wp.float64:
    """Model b's estimated distance to rest (mm) from the last measurement (see
    :class:`DistanceToRest`), meaningful from the third call on (``calls[b]`` >= 2 before it);
    updates the state for the next call."""
    calls = d.calls[b]
    remaining = wp.float64(wp.inf)
    if calls >= 1:
        change = wp.float64(d.largest[b]) / d.mm
        if calls >= 2:
            previous = d.change[b]
            rate = wp.float64(wp.inf)  # a model that stood still at the previous sample is not contracting
            if previous > wp.float64(0.0):
                rate = change / previous
            if rate < wp.float64(1.0):
                remaining = change * rate / (wp.float64(1.0) - rate)
            at_rest = change <= d.round_off_mm  # nothing left to contract
            if at_rest:
                remaining = change
            if calls >= 3:
                d.slowing[b] = wp.where((rate > d.rate[b] + d.slowing_ratio) and not at_rest, 1, 0)
            d.rate[b] = rate
        d.change[b] = change
    d.calls[b] = calls + 1
    return remaining


@wp.kernel
def distance_estimates(d: DistanceState, remaining: wp.array(dtype=wp.float64)):
    """:func:`estimate_distance` of every model."""
    b = wp.tid()
    remaining[b] = estimate_distance(d, b)


class DistanceToRest:
    """Estimated distance (mm) each of B models still has to travel, from its displacement
    sampled on the device: with c_k = max |u_k - u_(k-1)| between samples and r = c_k / c_(k-1)
    the observed contraction, the remaining travel of a geometric approach is c_k r / (1 - r)
    (inf while not contracting; the change itself once it is down to float32 round-off, where a
    model at rest - e.g. an exact affine solution - stops contracting). Changes over a whole
    sampling interval, not single steps, so that float32 round-off of the displacement (about
    1e-6 mm) does not drown the estimate near convergence.

    The estimate extrapolates the latest ratio, which holds only once the slowest motion left
    dominates the change; while a slower motion is taking over from a faster one that dies out,
    the ratio rises, and the estimate reads short. The state's ``slowing`` flags the models whose
    ratio rose by more than :data:`SLOWING` since the previous estimate (a relaxation does not
    trust their estimate then: one stopped 0.40 mm from rest on an estimate of 0.009 mm, its ratio
    0.54 -> 0.69, with a creeping mode 40 times slower than the Rayleigh quotient had found).

    :meth:`measure` is device work; a relaxation estimates on the device (:func:`estimate_distance`
    in :func:`relaxation_update`), a physical-time solve through :meth:`estimate`."""

    def __init__(self, like: wp.array, n_models: int) -> None:
        self._sample = wp.zeros_like(like)
        self._n_nodes = like.shape[0] // n_models
        self.state = DistanceState()
        self.state.largest = wp.zeros(n_models, dtype=float, device=like.device)
        self.state.change = wp.zeros(n_models, dtype=wp.float64, device=like.device)
        self.state.rate = wp.zeros(n_models, dtype=wp.float64, device=like.device)
        self.state.slowing = wp.zeros(n_models, dtype=int, device=like.device)
        self.state.calls = wp.zeros(n_models, dtype=int, device=like.device)
        self.state.mm, self.state.round_off_mm, self.state.slowing_ratio = MM, ROUND_OFF_MM, SLOWING
        self._remaining = wp.zeros(n_models, dtype=wp.float64, device=like.device)
        self._remaining_host = HostCopy(self._remaining)
        self._estimates = 0

    def measure(self, u: wp.array) -> None:
        """Device work of a sample (no host synchronisation, so it can be captured in a graph):
        the largest change of ``u`` (m) since the previous measurement; ``u`` kept for the next."""
        self.state.largest.zero_()
        k.reduction_launch(k.largest_change, self.state.largest.shape[0], self._n_nodes,
                           [u, self._sample, self._n_nodes, self.state.largest])
        wp.copy(self._sample, u)

    def keep(self, models: Selection) -> None:
        """Go on with the selected models of the batch only (see
        :mod:`~BreastBiomechLib.solver.packing`); device work."""
        self._sample = models.take(self._sample)
        for name in ("largest", "change", "rate", "slowing", "calls"):
            setattr(self.state, name, models.take(getattr(self.state, name)))
        self._remaining = models.take(self._remaining)
        self._remaining_host.follow(self._remaining)

    def estimate(self) -> np.ndarray | None:
        """(B,) estimates (mm) from the last :meth:`measure`, from the third estimate on; call
        once per measurement, at consecutive measurements (the first call only starts counting)."""
        wp.launch(distance_estimates, self._remaining.shape[0], [self.state, self._remaining])
        self._remaining_host.refresh()
        self._estimates += 1
        remaining = self._remaining_host.read()
        return remaining if self._estimates >= 3 else None


@wp.struct
class RelaxationState:
    """Per model b of the batch: ``active[b]`` 1 while it moves; updates since its load was complete,
    the update after which the least quotient sets its damping, updates in a row without
    contraction and with the estimate below the tolerance, the step it converged at; the
    kinetic energy at the previous update (J), the least Rayleigh quotient (1/s^2), the damping in
    float64 (1/s) and as the steps read it (``damping_now``, float32), the estimated error (mm);
    and its constants: the time its load is complete (s), its damping cap (1/s) and the float32
    noise floor of its displacement change (mm)."""
    active: wp.array(dtype=int)
    since_load: wp.array(dtype=int)
    settled_after: wp.array(dtype=int)
    stalled_updates: wp.array(dtype=int)
    checks_below: wp.array(dtype=int)
    converged_at: wp.array(dtype=int)
    ke_before: wp.array(dtype=wp.float64)
    lowest: wp.array(dtype=wp.float64)
    damping: wp.array(dtype=wp.float64)
    damping_now: wp.array(dtype=float)
    estimated_error: wp.array(dtype=wp.float64)
    loaded_at: wp.array(dtype=wp.float64)
    damping_cap: wp.array(dtype=wp.float64)
    noise_floor: wp.array(dtype=wp.float64)


@wp.struct
class RelaxationRules:
    """The batch's constants: time step (s), tolerance (mm), the largest damping (1/s), the rules'
    thresholds (see the module's constants), whether the relaxation starts warm, and the time (s)
    the first model of the batch is loaded (the batch as it started: models packed away later
    count)."""
    dt: wp.float64
    first_loaded_at: wp.float64
    tolerance_mm: wp.float64
    damping_limit: wp.float64
    surge: wp.float64
    moving: wp.float64
    chatter_quotient: wp.float64
    smallest_inertia: wp.float64
    settling_updates: int
    chatter_updates: int
    warm: int


@wp.kernel
def relaxation_update(s: RelaxationState, rules: RelaxationRules, distance: DistanceState,
                      kinetic: wp.array(dtype=float), internal: wp.array(dtype=float),
                      stiffness: wp.array(dtype=float), inertia: wp.array(dtype=float),
                      inverted: wp.array(dtype=int), clock: wp.array(dtype=int)):
    """One sample's decisions for model b (one thread per model), after the sample's energies
    (``kinetic`` J, ``internal`` twice the internal energy, J), Rayleigh-quotient terms and
    distance measurement (see :class:`BreastBiomechLib.solver.settings.DynamicRelaxation` for the
    rules): a model with an inverted element stops moving; once some model's load is complete,
    the distance to rest is estimated, the damping set and converged models stopped (frozen:
    ``inverted[4b + 3]`` = 2)."""
    b = wp.tid()
    step = clock[0]
    now = wp.float64(step) * rules.dt
    if inverted[4 * b] > 0:
        s.active[b] = 0
    if now < rules.first_loaded_at:  # no model of the batch is loaded yet
        return
    zero = wp.float64(0.0)
    two = wp.float64(2.0)
    active = s.active[b] == 1
    loaded = now >= s.loaded_at[b]
    lam = wp.float64(stiffness[b]) / wp.max(wp.float64(inertia[b]), rules.smallest_inertia)
    ke = wp.float64(kinetic[b])
    ie = wp.float64(0.5) * wp.float64(internal[b])
    estimated = distance.calls[b] >= 2
    remaining = estimate_distance(distance, b)
    since = s.since_load[b]
    if estimated and loaded:  # (a warm start is loaded before its first estimate)
        since = since + 1
        s.since_load[b] = since
    # a transient - the load's, or energy released after it (kinetic energy grown ``surge`` times
    # since the previous update) - is damped by the latest quotient, which its fast modes raise;
    # only then does the least quotient set the damping (lowered at once, it let a fit's 12 mm mesh
    # invert). A warm start's first updates are its trust delay only: its damping follows the
    # latest quotient
    settled_after = s.settled_after[b]
    if (loaded and rules.warm == 0 and since > settled_after and ke > rules.surge * s.ke_before[b]
            and ke > rules.moving * ie):
        settled_after = since + rules.settling_updates
        s.settled_after[b] = settled_after
    if loaded:
        s.ke_before[b] = ke
    settling = since <= settled_after
    warm = rules.warm != 0
    lowest = s.lowest[b]
    if loaded and (not settling or warm) and lam > zero and active:
        lowest = wp.min(lowest, lam)
        s.lowest[b] = lowest
    cap = s.damping_cap[b]
    following = wp.min(wp.min(two * wp.sqrt(wp.max(lam, zero)), rules.damping_limit), cap)
    least = wp.min(wp.min(two * wp.sqrt(wp.where(wp.isfinite(lowest), lowest, zero)), rules.damping_limit), cap)
    stalled = estimated and not wp.isfinite(remaining)
    stalled_updates = int(0)
    if stalled:
        stalled_updates = s.stalled_updates[b] + 1
    s.stalled_updates[b] = stalled_updates
    chatter = stalled_updates >= rules.chatter_updates and lam > rules.chatter_quotient * wp.min(lowest, lam)
    if lam > zero and loaded:
        if warm or settling or chatter or not wp.isfinite(lowest):
            s.damping[b] = following
        else:
            s.damping[b] = least
    s.damping_now[b] = float(s.damping[b])
    if estimated:
        running = active and loaded
        # a change below the model's float32 noise floor made of high modes only (its quotient far
        # above the least) is noise about the rest state, not a motion to extrapolate: its
        # contraction ratio jumps above and below 1
        change = distance.change[b]
        noise = change <= s.noise_floor[b] and wp.isfinite(lowest) and lam > rules.chatter_quotient * lowest
        if noise:
            remaining = wp.min(remaining, change)
        if running:
            s.estimated_error[b] = remaining
        trusted = (running and s.estimated_error[b] < rules.tolerance_mm
                   and (warm or distance.slowing[b] == 0 or noise))
        checks = int(0)
        if trusted:
            checks = s.checks_below[b] + 1
        s.checks_below[b] = checks
        # trust the estimate once the load's transient is over, where it is below the tolerance at
        # two checks in a row and the motion is not slowing down; the model stops (is frozen) as
        # soon as it has converged, the others of the batch go on
        if running and not settling and checks >= 2:
            s.active[b] = 0
            s.converged_at[b] = step
            inverted[4 * b + 3] = 2


class RelaxationControl:
    """The device state of a batch's relaxation (:class:`RelaxationState`) and its update.

    ``loaded_at`` (s) when each model's load is complete, ``damping`` its damping to start with,
    ``damping_now`` the steps' float32 damping array (updated in place), ``damping_cap`` and
    ``noise_floor`` per model (1/s, mm), ``dt`` (s), ``tolerance_mm``, ``warm`` a warm start."""

    def __init__(self, loaded_at: np.ndarray, damping: np.ndarray, damping_now: wp.array, damping_cap: np.ndarray,
                 noise_floor: np.ndarray, dt: float, tolerance_mm: float, warm: bool) -> None:
        n_models = len(loaded_at)
        device = damping_now.device

        def f64(values):
            return wp.array(np.asarray(values, np.float64), dtype=wp.float64, device=device)

        def ints(value):
            return wp.array(np.full(n_models, value, np.int32), dtype=int, device=device)

        s = RelaxationState()
        s.active, s.since_load, s.settled_after = ints(1), ints(0), ints(SETTLING_UPDATES)
        s.stalled_updates, s.checks_below, s.converged_at = ints(0), ints(0), ints(0)
        s.ke_before, s.lowest = f64(np.full(n_models, np.inf)), f64(np.full(n_models, np.inf))
        s.damping, s.damping_now = f64(damping), damping_now
        s.estimated_error = f64(np.full(n_models, np.nan))
        s.loaded_at, s.damping_cap, s.noise_floor = f64(loaded_at), f64(damping_cap), f64(noise_floor)
        self.state = s
        self.rules = RelaxationRules()
        self.rules.dt, self.rules.tolerance_mm, self.rules.damping_limit = dt, tolerance_mm, DAMPING_LIMIT / dt
        self.rules.first_loaded_at = float(np.min(loaded_at))
        self.rules.surge, self.rules.moving, self.rules.chatter_quotient = SURGE, MOVING, CHATTER_QUOTIENT
        self.rules.smallest_inertia = SMALLEST_INERTIA
        self.rules.settling_updates, self.rules.chatter_updates, self.rules.warm = (SETTLING_UPDATES, CHATTER_UPDATES,
                                                                                   int(warm))
        self.active = HostCopy(s.active)

    def update(self, distance: DistanceToRest, kinetic: wp.array, internal: wp.array, stiffness: wp.array,
               inertia: wp.array, inverted: wp.array, clock: wp.array) -> None:
        """Device work of a sample, after its measurements (see :func:`relaxation_update`); the
        models still active are copied for :attr:`active` to read."""
        wp.launch(relaxation_update, self.state.active.shape[0], [self.state, self.rules, distance.state, kinetic,
                                                                  internal, stiffness, inertia, inverted, clock])
        self.active.refresh()

    def keep(self, models: Selection, damping_now: wp.array) -> None:
        """Go on with the selected models of the batch only (see
        :mod:`~BreastBiomechLib.solver.packing`), whose float32 damping the steps now read from
        ``damping_now``; device work."""
        s = self.state
        for name in ("active", "since_load", "settled_after", "stalled_updates", "checks_below", "converged_at",
                     "ke_before", "lowest", "damping", "estimated_error", "loaded_at", "damping_cap", "noise_floor"):
            setattr(s, name, models.take(getattr(s, name)))
        s.damping_now = damping_now
        self.active.follow(s.active)
