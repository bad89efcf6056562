"""Static equilibrium by Newton's method in float64: the reference the explicit paths are checked
against.

Dynamic relaxation and a settled physical-time run both aim at the static solution of the same
discrete problem: internal forces of the T4 / T4ANP elements (materials fully relaxed) balance
gravity and the plate reactions, prescribed components take their final values, and no slave
node lies behind its plate. :func:`solve_static` finds it without any time integration: the load
is applied in increments, each solved by Newton's method with the exact tangent and with the
plates as an active set of equality constraints (Lagrange multipliers = contact forces,
released when they would pull). It runs on the CPU with NumPy/SciPy in double precision and a
sparse direct solver, so it suits models up to a few tens of thousands of elements; it exists
to decide, independently of damping, mass scaling and stopping criteria, where the explicit
solvers must end up.

Units as in :mod:`BreastBiomechLib.solver.model` outside (mm, Pa, kg/m^3, m/s^2); SI inside.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from BreastBiomechLib.solver.geometry import shape_derivatives
from BreastBiomechLib.solver.host_setup import anp_slots, merged_constraints
from BreastBiomechLib.solver.model import Model
from BreastBiomechLib.solver.settings import MM
from BreastBiomechLib.solver.solution import Solution

_FD_STEP = 1e-6  # central-difference step on the deformation gradient (dimensionless)
_MAX_BACKTRACKS = 10  # halvings of a Newton step that would invert elements
_DEGENERATE_J = 1e-6  # volume ratios at or below this count as inverted: their stress overflows


class InvertedElements(ValueError):
    """A displacement field turns elements inside out or flat (J, or the mean nodal J with ANP,
    at most ``_DEGENERATE_J``)."""

    def __init__(self, elements: np.ndarray):
        self.elements = elements
        super().__init__(f"{len(elements)} element(s) inverted (J <= 0), first {elements[:5].tolist()}")


class Discretisation:
    """The model's elements in SI with its fully relaxed materials: internal forces and their
    exact tangent for a displacement field (m), in double precision."""

    def __init__(self, model: Model):
        self.model = model
        self.tets = model.mesh.tets
        self.n_nodes = len(model.mesh.nodes)
        self.anp = model.formulation == "T4ANP"
        self.dhdx, self.vol = shape_derivatives(model.mesh.nodes * MM, self.tets)
        mat = model.materials.long_term()
        self.slots, self.slot_volume = anp_slots(self.tets, [mat], self.vol, model.anp_across_materials)
        self.mu, self.kappa, self.eta, self.fibre = mat.mu, mat.kappa, mat.eta, mat.fibre
        self.mass = np.bincount(self.tets.ravel(), weights=np.repeat(mat.density * self.vol / 4.0, 4),
                                minlength=self.n_nodes)
        # DOF index of each element's 12 displacement components, (M, 12): node a component i at 3a + i
        self.dofs = (3 * self.tets[:, :, None] + np.arange(3)).reshape(-1, 12)

    def deformation_gradient(self, u_m: np.ndarray) -> np.ndarray:
        """F = I + sum_a u_a (x) dN_a/dX per element, (M, 3, 3)."""
        return np.eye(3) + np.einsum("mai,maj->mij", u_m[self.tets], self.dhdx)

    def mean_nodal_jacobian(self, J: np.ndarray) -> np.ndarray:
        """ANP: each element's mean of its slots' (node and material) volume-weighted kappa (J - 1),
        as a volume ratio."""
        pv = np.bincount(self.slots.ravel(), weights=np.repeat(self.kappa * (J - 1.0) * self.vol, 4),
                         minlength=len(self.slot_volume)) / self.slot_volume
        return 0.25 * pv[self.slots].sum(axis=1) / self.kappa + 1.0

    def first_piola(self, F: np.ndarray, Jm: np.ndarray) -> np.ndarray:
        """P = Fbar S(Fbar), Fbar = (Jm / J)^(1/3) F (Pa), (M, 3, 3): the kernels' stress."""
        J = np.linalg.det(F)
        Fb = np.cbrt(Jm / J)[:, None, None] * F
        C = np.einsum("mki,mkj->mij", Fb, Fb)
        Cinv = np.linalg.inv(C)
        J23 = Jm ** (-2.0 / 3.0)
        trace = np.einsum("mii->m", C)
        S = (self.mu * J23)[:, None, None] * (np.eye(3) - (trace / 3.0)[:, None, None] * Cinv)
        a = self.fibre
        I4 = np.einsum("mi,mij,mj->m", a, C, a)
        fibre_term = 2.0 * self.eta * (J23 * I4 - 1.0) * J23
        S += fibre_term[:, None, None] * (np.einsum("mi,mj->mij", a, a) - (I4 / 3.0)[:, None, None] * Cinv)
        S += (self.kappa * Jm * (Jm - 1.0))[:, None, None] * Cinv
        return Fb @ S

    def state(self, u_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(F, Jm) per element; raises :class:`InvertedElements`."""
        F = self.deformation_gradient(u_m)
        J = np.linalg.det(F)
        Jm = self.mean_nodal_jacobian(J) if self.anp else J
        bad = np.flatnonzero((J <= _DEGENERATE_J) | (Jm <= _DEGENERATE_J))
        if len(bad):
            raise InvertedElements(bad)
        return F, Jm

    def forces(self, u_m: np.ndarray) -> np.ndarray:
        """Internal nodal forces (N, 3) in newtons."""
        F, Jm = self.state(u_m)
        fe = self.vol[:, None, None] * np.einsum("mij,maj->mai", self.first_piola(F, Jm), self.dhdx)
        return np.stack([np.bincount(self.tets.ravel(), weights=fe[:, :, i].ravel(), minlength=self.n_nodes)
                         for i in range(3)], axis=1)

    def tangent(self, u_m: np.ndarray) -> tuple[sp.csr_matrix, sp.csr_matrix | None, sp.csr_matrix | None]:
        """d forces / d u (N/m) in factored form (K, G, H): K (3N x 3N) the element part (at fixed
        mean nodal J with ANP), and with ANP the pressure coupling G (3N x S) and H (S x 3N), S the
        ANP slots (node and material), so that the full tangent is K + G H (None, None for T4).
        H du is the change of each slot's volume-weighted kappa (J - 1) divided by its volume,
        kappa_e' V_e' J_e' F_e'^-T : dF_e' summed over the slot's elements e'; G the change of the
        forces per unit change of it,
        through each element's mean over its nodes (1 / 4 kappa_e) and dP/dJm. Kept factored
        because the product couples nodes two element rings apart and fills a direct solver's
        factors. Exact up to the central differences of the element stress (relative ~1e-9)."""
        F, Jm = self.state(u_m)
        M, n = len(self.tets), 3 * self.n_nodes
        dPdF = np.empty((M, 3, 3, 3, 3))
        for k in range(3):
            for l in range(3):
                step = np.zeros((3, 3))
                step[k, l] = _FD_STEP
                plus, minus = F + step, F - step
                jp = Jm if self.anp else np.linalg.det(plus)
                jm = Jm if self.anp else np.linalg.det(minus)
                dPdF[:, :, :, k, l] = (self.first_piola(plus, jp) - self.first_piola(minus, jm)) / (2 * _FD_STEP)
        # K_e[(a,i),(b,k)] = V0 sum_jl dN_a,j dP_ij/dF_kl dN_b,l
        Ke = self.vol[:, None, None, None, None] * np.einsum("maj,mijkl,mbl->maibk", self.dhdx, dPdF, self.dhdx)
        rows = np.repeat(self.dofs, 12, axis=1).ravel()
        cols = np.tile(self.dofs, (1, 12)).ravel()
        K = sp.csr_matrix((Ke.reshape(M, 144).ravel(), (rows, cols)), shape=(n, n))
        if not self.anp:
            return K, None, None
        h = _FD_STEP * Jm
        dPdJ = (self.first_piola(F, Jm + h) - self.first_piola(F, Jm - h)) / (2 * h)[:, None, None]
        g = self.vol[:, None, None] * np.einsum("mij,maj->mai", dPdJ, self.dhdx) * (0.25 / self.kappa)[:, None, None]
        # G[(a,i), k] = sum over elements e containing a and k of g_e[a, i]
        G = sp.csr_matrix((np.repeat(g.reshape(M, 12), 4, axis=1).ravel(),
                           (np.repeat(self.dofs, 4, axis=1).ravel(), np.tile(self.slots, (1, 12)).ravel())),
                          shape=(n, len(self.slot_volume)))
        FinvT_dN = np.einsum("mlk,mal->mak", np.linalg.inv(F), self.dhdx)  # (F^-T dN_a)_k
        d = (self.kappa * self.vol * np.linalg.det(F))[:, None, None] * FinvT_dN
        per_slot = np.repeat(d.reshape(M, 1, 12), 4, axis=1) / self.slot_volume[self.slots][:, :, None]
        H = sp.csr_matrix((per_slot.ravel(),
                           (np.repeat(self.slots, 12, axis=1).ravel(), np.tile(self.dofs, (1, 4)).ravel())),
                          shape=(len(self.slot_volume), n))
        return K, G, H


def _plate_point(plate, fraction: float) -> np.ndarray:
    """A point on the plate at ``fraction`` of its travel (m)."""
    return (plate.point + fraction * plate.displacement) * MM


def _contact_rows(model: Model, positions_m: np.ndarray, fraction: float, active: list[set[int]]
                  ) -> tuple[list[tuple[int, int]], np.ndarray, np.ndarray]:
    """Active contact constraints as (plate, node) pairs, their gaps (m) and normals."""
    pairs, gaps, normals = [], [], []
    for p, plate in enumerate(model.loading.plates):
        point = _plate_point(plate, fraction)
        for node in sorted(active[p]):
            pairs.append((p, node))
            gaps.append(float((positions_m[node] - point) @ plate.normal))
            normals.append(plate.normal)
    return pairs, np.array(gaps), np.array(normals).reshape(-1, 3)


def _penetrating(model: Model, positions_m: np.ndarray, fraction: float, tolerance_m: float) -> list[set[int]]:
    """Per plate, the slave nodes lying behind it by more than ``tolerance_m``."""
    out = []
    for plate in model.loading.plates:
        gap = (positions_m[plate.slave_nodes] - _plate_point(plate, fraction)) @ plate.normal
        out.append(set(plate.slave_nodes[gap < -tolerance_m].tolist()))
    return out


def solve_static(model: Model, increments: int | None = None, tolerance_mm: float = 1e-6, max_newton: int = 25,
                 max_active_set_rounds: int = 30, max_cuts: int = 8,
                 initial_displacement: np.ndarray | None = None) -> Solution:
    """Static equilibrium of ``model`` at full load (plates at their final positions, prescribed
    components at their final values, full gravity), by incremental Newton iterations.

    Each of ``increments`` (10 by default) equal load steps is solved by Newton's method on the
    free components with the plates' active contact nodes held on them (Lagrange multipliers),
    until the largest correction is below ``tolerance_mm``; then nodes behind a plate join its active set and
    nodes the plate would pull leave it, and the step is solved again until the set no longer
    changes. A step that inverts elements or does not converge is halved, down to
    1/2^``max_cuts`` of the initial increment, and grows back after each step that converges.
    Returns a :class:`~BreastBiomechLib.solver.solution.Solution` with status
    ``completed``, ``not converged``, ``inverted elements`` or ``singular`` (the supports leave
    rigid motion free); ``steps`` counts Newton iterations, ``plate_forces`` are the contact
    forces each plate applies to the tissue (N), ``estimated_error_mm`` the last correction.
    ``history`` holds per converged increment its ``load_fraction``, ``newton_iterations`` and
    the ``plate_forces``.

    ``initial_displacement`` (N, 3) mm instead starts Newton at full load from that
    configuration, e.g. to polish an explicit solution or to test whether it is an equilibrium;
    its nodes on a plate (within 1e-4 mm) start in the active set."""
    if model.prestate is not None or model.loading.supports:
        raise ValueError("the static reference solver starts from a stress-free mesh with fixed supports; solve a "
                         "pre-stressed model or one with sliding or elastic supports by dynamic relaxation")
    rough = [plate.name for plate in model.loading.plates if plate.friction > 0]
    if rough:
        raise ValueError(f"the static reference solver has frictionless contact only; plates {rough} have friction: "
                         "solve with dynamic relaxation or in physical time")
    edged = [plate.name for plate in model.loading.plates if plate.edge is not None]
    if edged:
        raise ValueError(f"the static reference solver handles flat unbounded plates only; plates {edged} have a "
                         "rounded edge: solve with dynamic relaxation, or set their edge to None")
    started = time.perf_counter()
    disc = Discretisation(model)
    N = disc.n_nodes
    plates = model.loading.plates
    X = model.mesh.nodes * MM
    cnodes, cmask, cvalues = merged_constraints(model)
    fixed = np.zeros((N, 3), bool)
    fixed[cnodes] = cmask
    free = np.flatnonzero(~fixed.ravel())
    prescribed = np.zeros((N, 3))
    prescribed[cnodes] = np.where(cmask, cvalues, 0.0) * MM
    weight = disc.mass[:, None] * model.loading.gravity  # N
    tol_m = tolerance_mm * MM

    u = np.zeros((N, 3))
    active: list[set[int]] = [set() for _ in plates]
    if initial_displacement is not None:
        if increments is not None:
            raise ValueError("increments apply to a solve from rest; from an initial displacement the full load "
                             "is solved at once")
        u = np.asarray(initial_displacement, float).reshape(N, 3) * MM
        active = _penetrating(model, X + u, 1.0, -1e-4 * MM)  # on the plate within 1e-4 mm
        increments, max_cuts = 1, 0
    increments = 10 if increments is None else increments
    if increments < 1:
        raise ValueError("increments must be at least 1")
    history = {"load_fraction": [], "newton_iterations": [], "plate_forces": []}
    iterations, last_correction, forces_on_tissue = 0, float("inf"), np.zeros((len(plates), 3))
    done, step = 0.0, 1.0 / increments
    smallest = step / 2.0**max_cuts

    def result(status: str, message: str) -> Solution:
        return Solution(u / MM, forces_on_tissue, status, message, iterations, float("nan"),
                        time.perf_counter() - started, float("nan"),
                        {key: np.array(v) for key, v in history.items()}, last_correction / MM,
                        plate_normals=np.array([p.normal for p in model.loading.plates]).reshape(-1, 3))

    while done < 1.0 - 1e-12:
        target = min(1.0, done + step)
        trial = u.copy()
        trial[fixed] = target * prescribed[fixed]
        trial_active = [a | b for a, b in zip(active, _penetrating(model, X + trial, target, 0.0))]
        outcome = _solve_increment(model, disc, trial, trial_active, free, target, weight, tol_m, max_newton,
                                   max_active_set_rounds)
        if isinstance(outcome, str):
            if outcome == "singular":
                return result("singular", "the tangent stiffness is singular: the supports leave rigid motion "
                                        "free; fix more components (see solver.supports.support_constraints)")
            if step / 2.0 < smallest * (1.0 - 1e-9):
                status = "inverted elements" if outcome == "inverted" else "not converged"
                if initial_displacement is not None:
                    return result(status, f"Newton's method from the given displacement failed ({outcome}); "
                                        "solve from rest instead")
                return result(status, f"the load step from {done:.4g} of the full load failed ({outcome}) even "
                                    f"at 1/{2**max_cuts} of the initial increment; use more increments or check "
                                    "the loading")
            step /= 2.0
            continue
        u, active, n_iter, last_correction, forces_on_tissue = outcome
        iterations += n_iter
        done, step = target, min(2.0 * step, 1.0 / increments)
        history["load_fraction"].append(done)
        history["newton_iterations"].append(n_iter)
        history["plate_forces"].append(forces_on_tissue.copy())
    return result("completed", f"static equilibrium in {len(history['load_fraction'])} load steps, {iterations} "
                               f"Newton iterations, last correction {last_correction / MM:.2g} mm")


def _solve_increment(model, disc, u, active, free, fraction, weight, tol_m, max_newton, max_rounds):
    """Newton iterations with an active-set loop at one load level. Returns (u, active,
    iterations, last correction (m), plate forces) or the reason it failed: "inverted",
    "not converged", "singular"."""
    X = model.mesh.nodes * MM
    N = disc.n_nodes
    plates = model.loading.plates
    iterations = 0
    for _ in range(max_rounds):
        for _ in range(max_newton):
            try:
                residual = disc.forces(u) - fraction * weight
            except InvertedElements:
                return "inverted"
            pairs, gaps, normals = _contact_rows(model, X + u, fraction, active)
            try:
                solution = _newton_correction(disc.tangent(u), free, pairs, normals, residual, gaps)
            except RuntimeError:
                return "singular"
            du = np.zeros(3 * N)
            du[free] = solution[:len(free)]
            du = du.reshape(N, 3)
            iterations += 1
            for halvings in range(_MAX_BACKTRACKS):  # shorten a step that would turn elements inside out
                try:
                    disc.state(u + du)
                    break
                except InvertedElements:
                    du = 0.5 * du
            else:
                return "inverted"
            correction = float(np.abs(du).max())
            u = u + du
            if correction < tol_m and halvings == 0:
                break
        else:
            return "not converged"
        try:
            residual = disc.forces(u) - fraction * weight
        except InvertedElements:
            return "inverted"
        pairs, gaps, normals = _contact_rows(model, X + u, fraction, active)
        # contact force on the tissue along the normal: the internal force the plate balances
        push = np.array([residual[node] @ n for (p, node), n in zip(pairs, normals)])
        pulling = {pair for pair, f in zip(pairs, push) if f < 0}
        entering = _penetrating(model, X + u, fraction, tol_m)
        changed = bool(pulling) or any(entering[p] - active[p] for p in range(len(plates)))
        if not changed:
            forces = np.zeros((len(plates), 3))
            for (p, node), f, n in zip(pairs, push, normals):
                forces[p] += f * n
            return u, active, iterations, correction, forces
        active = [(active[p] | entering[p]) - {node for q, node in pulling if q == p} for p in range(len(plates))]
    return "not converged"


def _newton_correction(tangent, free, pairs, normals, residual, gaps) -> np.ndarray:
    """Solve for the correction of the free components (first ``len(free)`` entries of the
    result) with the active contact nodes' normal gaps closed. With ANP the tangent K + G H is
    kept factored through one extra unknown per node, q = H du:
    [[K, G, -C^T], [H, -I, 0], [C, 0, 0]] [du, q, lambda] = [-r, 0, -gap]."""
    K, G, H = tangent
    n = K.shape[0]
    C = sp.csr_matrix((normals.ravel(), (np.repeat(np.arange(len(pairs)), 3),
                                         (3 * np.array([node for _, node in pairs], int)[:, None]
                                          + np.arange(3)).ravel())), shape=(len(pairs), n))[:, free]
    K = K[free][:, free]
    if G is None:
        blocks = [[K, -C.T], [C, None]]
        rhs = [-residual.ravel()[free], -gaps]
    else:
        blocks = [[K, G[free], -C.T], [H[:, free], -sp.identity(G.shape[1]), None], [C, None, None]]
        rhs = [-residual.ravel()[free], np.zeros(G.shape[1]), -gaps]
    if len(pairs) == 0:
        blocks = [row[:-1] for row in blocks[:-1]]
        rhs = rhs[:-1]
    A, b = sp.bmat(blocks, format="csr"), np.concatenate(rhs)
    solution = _sparse_solve(A, b)
    # a singular system gives NaN (SuperLU) or a huge solution of a perturbed one (PARDISO)
    if not np.all(np.isfinite(solution)) or np.abs(A @ solution - b).max() > 1e-6 * max(np.abs(b).max(), 1e-30):
        raise RuntimeError("singular tangent")
    return solution


def _sparse_solve(A: sp.csr_matrix, b: np.ndarray) -> np.ndarray:
    """A x = b by a sparse direct solver: MKL PARDISO through ``pypardiso`` when it is installed
    (about 10x faster than SuperLU on the 40k-tet breast), SciPy's SuperLU otherwise."""
    try:
        import pypardiso
    except ImportError:
        with np.errstate(all="ignore"):
            return spla.spsolve(A.tocsc(), b)
    solver = pypardiso.PyPardisoSolver()
    try:
        return solver.solve(A, b)
    except pypardiso.pardiso_wrapper.PyPardisoError:  # structurally singular: report it like SuperLU does
        return np.full_like(b, np.nan)
    finally:
        solver.free_memory(everything=True)
