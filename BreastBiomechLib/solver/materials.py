"""Hyperelastic materials of the solver: neo-Hookean (NH) and transversely isotropic NH (TI).

Strain energy with the isochoric/volumetric split (C-bar = J^(-2/3) C), as in NiftySim and the
seed's eq. (8):

    NH: W = mu/2 (I1bar - 3) + kappa/2 (J - 1)^2
    TI: W = NH + eta/2 (I4bar - 1)^2,   I4bar = a . Cbar a,  a the unit fibre direction

Parameters in pascal; mu = E / (2 (1 + nu)), kappa = E / (3 (1 - 2 nu)). eta is eq. (8)'s;
NiftySim's code takes 2 eta for the same fibre stress (see :mod:`BreastBiomechLib.io.niftysim`).

Visco-hyperelastic variants (NiftySim's NHV/TIV) relax the isochoric stress with a Prony series
g(t) = g_inf + sum_i g_i exp(-t / tau_i), g_inf = 1 - sum_i g_i: the instantaneous response is
the hyperelastic one above, the long-term response has mu and eta scaled by g_inf. The
volumetric response stays elastic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from BreastBiomechLib import labels


def lame_from_young(E, nu) -> tuple[np.ndarray, np.ndarray]:
    """(mu, kappa) in Pa from Young's modulus ``E`` (Pa) and Poisson's ratio ``nu`` (< 0.5)."""
    E = np.asarray(E, dtype=np.float64)
    nu = np.asarray(nu, dtype=np.float64)
    if np.any(E <= 0):
        raise ValueError("Young's modulus must be positive (Pa)")
    if np.any((nu <= -1.0) | (nu >= 0.5)):
        raise ValueError("Poisson's ratio must lie in (-1, 0.5); use 0.45-0.4999 for soft tissue")
    return E / (2.0 * (1.0 + nu)), E / (3.0 * (1.0 - 2.0 * nu))


def fibre_direction(gamma, alpha) -> np.ndarray:
    """Unit fibre vector from the seed's eq. (6) angles (radians):
    A = (sin g cos a, sin g sin a, cos g); gamma from e3 in [0, pi/2], alpha from e1 in [0, pi].

    (The seed prints cos(alpha) for the third component; cos(gamma) is the unit-vector form that
    matches its description of gamma as the angle between A and e3.)"""
    gamma = np.asarray(gamma, dtype=np.float64)
    alpha = np.asarray(alpha, dtype=np.float64)
    return np.stack([np.sin(gamma) * np.cos(alpha), np.sin(gamma) * np.sin(alpha), np.cos(gamma)], axis=-1)


def check_prony(g: np.ndarray, tau: np.ndarray) -> None:
    """Prony weights g (M, K) in [0, 1) summing to < 1 per element, time constants tau > 0 s."""
    if np.any(g < 0) or np.any(g.sum(axis=1) >= 1.0):
        raise ValueError("Prony weights g_i must be >= 0 and sum to less than 1 (g_inf = 1 - sum g_i > 0)")
    if np.any(tau[g > 0] <= 0):
        raise ValueError("Prony time constants tau_i must be positive (s)")


def labels_present(labels: np.ndarray) -> list:
    """The distinct values of ``labels`` in increasing order, as ``np.unique(labels).tolist()``;
    for integer labels of a small range by counting (a fit asks this of the same tissue labels
    twice a solve: np.unique's hashing of 54k labels took 1.3 ms, a count 0.1)."""
    labels = np.asarray(labels)
    if labels.size and labels.dtype.kind in "iu":
        low, high = int(labels.min()), int(labels.max())
        if high - low < 65536:
            return (np.flatnonzero(np.bincount((labels - low).ravel())) + low).tolist()
    return np.unique(labels).tolist()


@dataclass(frozen=True)
class Material:
    """One tissue's material: ``E`` (Pa, instantaneous), ``nu``, ``eta`` (Pa; 0 = isotropic NH),
    fibre direction (unit vector, LPS), density (kg/m^3), and ``prony``: (g_i, tau_i) pairs,
    relative weights and time constants (s) of the isochoric relaxation (empty = hyperelastic)."""

    E: float
    nu: float
    eta: float = 0.0
    fibre: tuple[float, float, float] = (0.0, 0.0, 1.0)
    density: float = 1000.0
    prony: tuple[tuple[float, float], ...] = ()

    def __post_init__(self) -> None:
        lame_from_young(self.E, self.nu)
        object.__setattr__(self, "prony", tuple((float(g), float(tau)) for g, tau in self.prony))
        check_prony(np.array([[g for g, _ in self.prony]]), np.array([[tau for _, tau in self.prony]]))
        if self.eta < 0:
            raise ValueError("eta (fibre reinforcement) must be >= 0 Pa")
        if self.density <= 0:
            raise ValueError("density must be positive (kg/m^3)")
        if not np.isclose(np.linalg.norm(self.fibre), 1.0, atol=1e-6):
            raise ValueError(f"fibre direction {self.fibre} must be a unit vector")

    @property
    def mu(self) -> float:
        return float(lame_from_young(self.E, self.nu)[0])

    @property
    def kappa(self) -> float:
        return float(lame_from_young(self.E, self.nu)[1])


@dataclass
class ElementMaterials:
    """Per-element material arrays (length M): mu, kappa, eta in Pa (instantaneous), fibre (M, 3)
    unit vectors, density kg/m^3, and Prony weights ``prony_g`` and time constants ``prony_tau``
    (s), both (M, K) (K = 0: hyperelastic; unused terms have g = 0). Heterogeneous models are just
    different values."""

    mu: np.ndarray
    kappa: np.ndarray
    eta: np.ndarray
    fibre: np.ndarray
    density: np.ndarray
    prony_g: np.ndarray | None = None
    prony_tau: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.mu = np.asarray(self.mu, np.float64)
        m = self.mu.shape[0]
        self.kappa = np.broadcast_to(np.asarray(self.kappa, np.float64), (m,)).copy()
        self.eta = np.broadcast_to(np.asarray(self.eta, np.float64), (m,)).copy()
        self.density = np.broadcast_to(np.asarray(self.density, np.float64), (m,)).copy()
        self.fibre = np.broadcast_to(np.asarray(self.fibre, np.float64), (m, 3)).copy()
        # Prony terms: (K,) for every element or (M, K)
        g = np.atleast_2d(np.zeros(0) if self.prony_g is None else np.asarray(self.prony_g, np.float64))
        tau = np.atleast_2d(np.ones(g.shape[1]) if self.prony_tau is None else np.asarray(self.prony_tau, np.float64))
        if tau.shape[1] != g.shape[1]:
            raise ValueError("give as many Prony time constants as weights")
        self.prony_g = np.broadcast_to(g, (m, g.shape[1])).copy()
        self.prony_tau = np.broadcast_to(tau, (m, g.shape[1])).copy()
        norms = np.linalg.norm(self.fibre, axis=1)
        if np.any(np.abs(norms - 1.0) > 1e-6):
            raise ValueError("fibre directions must be unit vectors")
        if np.any(self.mu <= 0) or np.any(self.kappa <= 0) or np.any(self.density <= 0):
            raise ValueError("mu, kappa and density must be positive in every element")
        check_prony(self.prony_g, self.prony_tau)

    def with_skin(self, fraction, skin: "Material") -> "ElementMaterials":
        """These materials with a skin layer by partial-volume (Voigt) weighting: in an element a
        share ``fraction`` (M,) in [0, 1] of whose volume lies in the layer, mu, kappa and density
        become (1 - f) x its own + f x the ``skin``'s, and eta and the Prony weights (1 - f) x its
        own (the skin is isotropic and elastic). Stiffnesses in parallel: the layer carries the
        in-plane (membrane) load beside the tissue under it, which is what skin does to a
        compressed breast; the element count stays. :mod:`BreastBiomechLib.mesh.skin` gives the
        fractions."""
        f = np.asarray(fraction, np.float64).reshape(-1)
        if f.shape != self.mu.shape or np.any(~np.isfinite(f)) or np.any((f < 0) | (f > 1)):
            raise ValueError(f"skin fractions must be {len(self.mu)} numbers in [0, 1]")
        return ElementMaterials((1 - f) * self.mu + f * skin.mu, (1 - f) * self.kappa + f * skin.kappa,
                                (1 - f) * self.eta, self.fibre, (1 - f) * self.density + f * skin.density,
                                (1 - f)[:, None] * self.prony_g, self.prony_tau)

    @property
    def prony_terms(self) -> int:
        """Number of Prony terms K (0 for hyperelastic materials)."""
        return self.prony_g.shape[1]

    def long_term(self) -> "ElementMaterials":
        """The fully relaxed (equilibrium) hyperelastic materials: mu and eta scaled by g_inf
        (these materials themselves where they have no Prony terms)."""
        if self.prony_terms == 0:
            return self
        g_inf = 1.0 - self.prony_g.sum(axis=1)
        return ElementMaterials(self.mu * g_inf, self.kappa, self.eta * g_inf, self.fibre, self.density)

    # set by from_tissues: its per-tissue table (the values as an ElementMaterials of one row per
    # tissue), each element's row, and the per-element arrays made from them (see `rows`)
    _rows = None

    @classmethod
    def from_tissues(cls, tissue: np.ndarray, materials: dict[int, Material]) -> "ElementMaterials":
        """Per-element arrays from element tissue labels and a {label: Material} table. The
        arrays are read-only; the materials keep the table they came from (:attr:`rows`)."""
        tissue = np.asarray(tissue)
        missing = sorted(set(labels_present(tissue)) - set(materials))
        if missing:
            raise ValueError(f"no material given for tissue labels {missing}")
        labels = sorted(materials)
        index = np.searchsorted(labels, tissue)  # each element's row in the per-tissue table
        table = [materials[t] for t in labels]
        terms = max(len(m.prony) for m in table)
        g = np.zeros((len(table), terms))
        tau = np.ones((len(table), terms))
        for row, m in enumerate(table):
            for col, (gi, ti) in enumerate(m.prony):
                g[row, col], tau[row, col] = gi, ti
        # each Material checked its own values: the per-element arrays need no second check (a
        # fit builds one set per evaluation, and the checks of 54k elements took 2 ms a set)
        per_tissue = cls._checked(mu=np.array([m.mu for m in table]), kappa=np.array([m.kappa for m in table]),
                                  eta=np.array([m.eta for m in table]),
                                  fibre=np.array([m.fibre for m in table], np.float64).reshape(-1, 3),
                                  density=np.array([m.density for m in table]), prony_g=g, prony_tau=tau)
        elements = cls._checked(**{name: getattr(per_tissue, name)[index] for name in _FIELDS})
        for name in _FIELDS:
            getattr(elements, name).flags.writeable = False
            getattr(per_tissue, name).flags.writeable = False
        index.flags.writeable = False
        elements._rows = (per_tissue, index, tuple(getattr(elements, name) for name in _FIELDS))
        return elements

    @property
    def rows(self) -> "tuple[ElementMaterials, np.ndarray] | None":
        """(table, row): materials made by :meth:`from_tissues` hold one value per tissue,
        ``table`` (an ElementMaterials of one row per tissue of the table it was given) and
        each element's row of it, ``row`` (M,); None for other materials, once a field has been
        given another array, or where one could have been changed in place (writeable again, as
        unpickled arrays are)."""
        if self._rows is None:
            return None
        table, row, arrays = self._rows
        if any(getattr(self, name) is not array or array.flags.writeable for name, array in zip(_FIELDS, arrays)):
            return None
        return table, row

    @classmethod
    def _checked(cls, **arrays: np.ndarray) -> "ElementMaterials":
        """Materials of per-element float64 ``arrays`` (every field, in the shapes
        :meth:`__post_init__` makes) whose values are known to pass its checks, without them."""
        materials = cls.__new__(cls)
        for name, values in arrays.items():
            setattr(materials, name, values)
        return materials

    @classmethod
    def uniform(cls, n_elements: int, material: Material) -> "ElementMaterials":
        return cls.from_tissues(np.zeros(n_elements, int), {0: material})


_FIELDS = ("mu", "kappa", "eta", "fibre", "density", "prony_g", "prony_tau")  # ElementMaterials' arrays


def equal_value_groups(columns_per_set) -> np.ndarray:
    """(M,) a group number per element: elements whose values agree in every column of every
    set share a group, numbered in the lexicographic order of their values (as
    ``np.unique(all columns, axis=0)`` would, without sorting rows of B x columns values: the
    sets of a batch mostly share one partition into tissues, which the first set finds and the
    others only confirm). ``columns_per_set``: per set, an iterable of (M,) arrays, compared
    exactly in their own precision (made as they are needed, if it is a generator)."""
    group = first = None
    for columns in columns_per_set:
        for values in columns:
            values = np.asarray(values)
            if group is not None and np.array_equal(values, values[first][group]):
                continue  # constant on every group: splits none
            _, rank = np.unique(values, return_inverse=True)
            rank = rank.ravel().astype(np.int64)
            if group is None:
                group = rank
            else:
                _, group = np.unique(group * (int(rank.max()) + 1) + rank, return_inverse=True)
                group = group.ravel().astype(np.int64)
            first = np.zeros(int(group.max()) + 1, np.int64)
            first[group] = np.arange(len(group))  # one element of each group
    if group is None:
        raise ValueError("equal_value_groups needs at least one column")
    return group


def element_groups(materials: list[ElementMaterials], columns) -> np.ndarray:
    """``equal_value_groups`` of the sets' ``columns(m)`` (an iterable of (M,) arrays of set m),
    the same groups numbered the same; where every set came from one tissue labelling
    (:attr:`ElementMaterials.rows`) the values are compared per tissue, not per element (a
    fit's batch of 16 sets of 54k elements: 24-26 ms a batch, against 1-3)."""
    shared = [m.rows for m in materials]
    if any(r is None for r in shared) or any(not np.array_equal(r[1], shared[0][1]) for r in shared[1:]):
        return equal_value_groups(columns(m) for m in materials)
    row = shared[0][1]
    present = np.flatnonzero(np.bincount(row.ravel(), minlength=len(shared[0][0].mu)))  # tissues in the mesh
    group_of_row = np.full(len(shared[0][0].mu), -1, np.int64)
    group_of_row[present] = equal_value_groups(([np.asarray(v)[present] for v in columns(table)]
                                                for table, _ in shared))
    return group_of_row[row]


def default_tissue_materials() -> dict[int, Material]:
    """Starting materials per tissue label (:mod:`BreastBiomechLib.labels`): isotropic NH,
    nu = 0.49, 1000 kg/m^3. Fat is the seed's reference (E_f = 10 kPa); the other tissues are
    round multiples in the order reported ex vivo (glandular 2x, skin 5x, muscle and tumour 10x
    fat). They are initial values for the optimiser (seed section 2.4, step 1), not measurements."""
    multiples = {labels.FAT: 1.0, labels.GLANDULAR: 2.0, labels.MUSCLE: 10.0, labels.TUMOUR: 10.0, labels.SKIN: 5.0}
    return {tissue.label: Material(E=10e3 * factor, nu=0.49) for tissue, factor in multiples.items()}
