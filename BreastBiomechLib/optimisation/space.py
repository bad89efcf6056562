"""The parameters an optimisation searches (seed section 2.4 and section 3.2): per tissue
Young's modulus E, Poisson's ratio nu and the fibre stiffness eta of the transversely isotropic
neo-Hookean model, with the seed's bounds; optionally the fibre direction's angles (seed eq. (6))
and the plates' final positions; the four model variants of the seed's Tables 2 and 3.

Units: E and eta in Pa, nu dimensionless, fibre angles in degrees, plate offsets in mm, fibre
directions unit vectors (LPS). Fat is the reference: the plates prescribe displacements, so
only stiffness ratios shape the deformation, and fat's E stays at E_f = 10 kPa (the seed's
choice). Optimisers work in the unit cube: each free parameter maps [0, 1] onto its bounds on a
log scale for E and eta (they span decades), on log(0.5 - nu) for nu (the bulk modulus,
1 / (1 - 2 nu), is what nu controls near 0.5), linearly for angles and offsets.

The fibre angles follow the seed's eq. (6) in LPS axes (e1 = L, e2 = P, e3 = S):
A = (sin gamma cos alpha, sin gamma sin alpha, cos gamma), gamma the angle between A and S,
alpha the azimuth from L towards P. (The seed prints cos alpha as the third component, which
would not give a unit vector; cos gamma is meant.) A fibre family has no sign, so gamma in
[0, 90] with alpha in [0, 360) reaches every direction; the seed's alpha in [0, 180] reaches
only half of them, so the default bounds take alpha in [0, 360).

A plate offset moves a plate's measured final plane along its normal (towards the tissue for
a positive offset, i.e. more compression): for a measured plate position that is uncertain.
Plates are named ``plate1``, ``plate2``, ... in the order of the case's plates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from BreastBiomechLib import labels
from BreastBiomechLib.solver.materials import ElementMaterials, Material, labels_present

MODELS = ("iso-homo", "iso-hetero", "aniso-homo", "aniso-hetero")
BOUNDS = {"E": (100.0, 1e6), "nu": (0.45, 0.4999), "eta": (1.0, 1e6)}  # the seed's section 3.2
FIBRE = "fibre"  # the fibre angles' owner in parameter keys ("fibre.gamma", "fibre.alpha")
GEOMETRY_BOUNDS = {"gamma": (0.0, 90.0), "alpha": (0.0, 360.0), "offset": (-5.0, 5.0)}  # degrees, degrees, mm
REFERENCE_E = 10e3  # E_f, fat's Young's modulus (Pa)
HOMOGENEOUS = "breast"  # the one material of a homogeneous model
STARTING = {"E": REFERENCE_E, "nu": 0.49, "eta": 1e3}  # values of parameters that are not free


@dataclass(frozen=True)
class FreeParameter:
    """One searched parameter: ``tissue`` (a tissue name, "breast" for the one material of a
    homogeneous model, "fibre" for the fibre angles, "plateN" for the N-th plate's offset),
    ``name`` ("E", "nu", "eta"; "gamma", "alpha"; "offset") and its bounds (Pa, -, Pa; degrees; mm)."""

    tissue: str
    name: str
    lower: float
    upper: float

    def __post_init__(self) -> None:
        if self.name not in BOUNDS and self.name not in GEOMETRY_BOUNDS:
            raise ValueError(f"{self.key}: free parameters are {sorted(BOUNDS) + sorted(GEOMETRY_BOUNDS)}")
        if self.name in ("gamma", "alpha") and self.tissue != FIBRE:
            raise ValueError(f"{self.key}: the fibre angles are {FIBRE}.gamma and {FIBRE}.alpha")
        if self.name == "offset" and not _is_plate(self.tissue):
            raise ValueError(f"{self.key}: plate offsets are plate1.offset, plate2.offset, ...")
        if not self.lower < self.upper or (self.logarithmic and not self.lower > 0):
            raise ValueError(f"{self.key}: the bounds must satisfy {'0 < ' * self.logarithmic}lower < upper, "
                             f"not [{self.lower}, {self.upper}]")
        if self.name == "nu" and self.upper >= 0.5:
            raise ValueError(f"{self.key}: Poisson's ratio must stay below 0.5")
        if self.name == "gamma" and not 0.0 <= self.lower < self.upper <= 180.0:
            raise ValueError(f"{self.key}: gamma (degrees) lies in [0, 180]")

    @property
    def logarithmic(self) -> bool:
        """Whether the parameter is searched on a log scale (E, nu through 0.5 - nu, eta)."""
        return self.name in BOUNDS

    @property
    def geometric(self) -> bool:
        """Whether the parameter is a fibre angle or a plate offset rather than a material's."""
        return self.name in GEOMETRY_BOUNDS

    @property
    def key(self) -> str:
        return f"{self.tissue}.{self.name}"

    def _scaled(self, value):
        value = np.asarray(value, float)
        if not self.logarithmic:
            return value
        return np.log(0.5 - value) if self.name == "nu" else np.log(value)

    def to_unit(self, value) -> np.ndarray:
        """The position of ``value`` in [0, 1] (0 at the lower bound)."""
        low, high = self._scaled(self.lower), self._scaled(self.upper)
        return (self._scaled(value) - low) / (high - low)

    def from_unit(self, z) -> np.ndarray:
        """The value at unit position ``z`` (clipped to [0, 1])."""
        low, high = self._scaled(self.lower), self._scaled(self.upper)
        scaled = low + np.clip(np.asarray(z, float), 0.0, 1.0) * (high - low)
        if not self.logarithmic:
            return scaled
        return 0.5 - np.exp(scaled) if self.name == "nu" else np.exp(scaled)


def _is_plate(name: str) -> bool:
    return name.startswith("plate") and name[5:].isdigit() and int(name[5:]) >= 1


def fibre_angles(direction) -> tuple[float, float]:
    """(gamma, alpha) in degrees of a fibre ``direction`` (LPS; either sign): gamma in [0, 90]
    from S, alpha in [0, 360) from L towards P (0 where gamma is 0)."""
    a = np.asarray(direction, float) / np.linalg.norm(direction)
    if a[2] < 0:
        a = -a
    gamma = float(np.degrees(np.arccos(np.clip(a[2], -1.0, 1.0))))
    alpha = float(np.degrees(np.arctan2(a[1], a[0]))) % 360.0 if np.hypot(a[0], a[1]) > 1e-12 else 0.0
    return gamma, alpha


def fibre_direction(gamma_deg: float, alpha_deg: float) -> np.ndarray:
    """The unit fibre direction (LPS) at angles ``gamma_deg`` from S and ``alpha_deg`` from L
    towards P (the seed's eq. (6))."""
    g, a = np.radians(gamma_deg), np.radians(alpha_deg)
    return np.array([np.sin(g) * np.cos(a), np.sin(g) * np.sin(a), np.cos(g)])


@dataclass
class ParameterSpace:
    """What an optimisation searches: the ``free`` parameters and the ``fixed`` values of every
    material ({tissue or "breast": {"E", "nu", "eta"}}), for a model variant of :data:`MODELS`
    on a mesh holding ``tissues`` (names). ``fibre``: the unit fibre direction (LPS) of the
    anisotropic variants (where its angles are free: the angles not free, and the start);
    ``plates``: how many plates the case has (their offsets may be free)."""

    model: str
    tissues: list[str]
    free: list[FreeParameter]
    fixed: dict[str, dict[str, float]]
    fibre: tuple[float, float, float] = (0.0, 0.0, 1.0)
    plates: int = 0

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"unknown model {self.model!r}; choose one of {MODELS}")
        fibre = np.asarray(self.fibre, float)
        if fibre.shape != (3,) or not np.isclose(np.linalg.norm(fibre), 1.0, atol=1e-6):
            raise ValueError("the fibre direction must be a unit 3-vector (LPS)")
        self.fibre = tuple(float(v) for v in fibre)
        keys = [p.key for p in self.free]
        if len(set(keys)) != len(keys):
            raise ValueError(f"a parameter is free twice: {keys}")
        materials = self.material_names
        for p in self.free:
            if p.name in ("gamma", "alpha") and not self.anisotropic:
                raise ValueError(f"{p.key}: the {self.model} model has no fibres; fit the fibre direction "
                                 "with an anisotropic variant")
            if p.name == "offset" and int(p.tissue[5:]) > self.plates:
                raise ValueError(f"{p.key}: the case has {self.plates} plate(s)")
            if not p.geometric and p.tissue not in materials:
                raise ValueError(f"{p.key}: the {self.model} model has materials {materials}")

    @property
    def homogeneous(self) -> bool:
        return self.model.endswith("homo")

    @property
    def anisotropic(self) -> bool:
        return self.model.startswith("aniso")

    @property
    def material_names(self) -> list[str]:
        """The model's materials: "breast" for a homogeneous model, else the tissues."""
        return [HOMOGENEOUS] if self.homogeneous else list(self.tissues)

    @property
    def dimension(self) -> int:
        return len(self.free)

    @property
    def keys(self) -> list[str]:
        return [p.key for p in self.free]

    @classmethod
    def for_model(cls, model: str, tissues, free=("E", "nu", "eta"), bounds: dict | None = None,
                  fibre=(0.0, 0.0, 1.0), start: dict | None = None, plates: int = 0) -> "ParameterSpace":
        """The seed's variant ``model`` on a mesh with ``tissues`` (names or labels): each
        material's parameters named in ``free`` are searched within the seed's bounds (or
        ``bounds``: {"E" | "nu" | "eta" or "tissue.name": (lower, upper)}), except fat's E (the
        reference) and, for isotropic variants, eta (zero). Parameters not free keep ``start``
        ({"tissue.name": value}) or the starting values (E_f, nu 0.49, eta 1 kPa). "fibre" in
        ``free`` also searches the fibre direction's angles (anisotropic variants; bounds
        "gamma", "alpha" or "fibre.gamma", "fibre.alpha" in degrees), "offset" every one of the
        case's ``plates``' offset along its normal (bounds "offset" or "plateN.offset", mm)."""
        if model not in MODELS:
            raise ValueError(f"unknown model {model!r}; choose one of {MODELS}")
        unknown = set(free) - set(BOUNDS) - {"fibre", "offset"}
        if unknown:
            raise ValueError(f"unknown free parameters {sorted(unknown)}; choose among "
                             f"{sorted(BOUNDS) + ['fibre', 'offset']}")
        if "fibre" in free and not model.startswith("aniso"):
            raise ValueError(f"the {model} model has no fibres: free the fibre direction with an anisotropic variant")
        if "offset" in free and plates < 1:
            raise ValueError("plate offsets need the case's plates (plates >= 1)")
        present = {labels.tissue(t if isinstance(t, str) else int(t)).name for t in tissues}
        names = [t.name for t in labels.TISSUES if t.name in present]  # label-table order
        if not names:
            raise ValueError("the mesh holds no tissue of the label table")
        bounds = dict(bounds or {})
        start = dict(start or {})
        homogeneous = model.endswith("homo")
        anisotropic = model.startswith("aniso")
        materials = [HOMOGENEOUS] if homogeneous else names
        searched, fixed = [], {}
        for material in materials:
            values = {}
            for name in ("E", "nu", "eta"):
                key = f"{material}.{name}"
                reference = name == "E" and material in ("fat", HOMOGENEOUS)
                if name == "eta" and not anisotropic:
                    values[name] = 0.0
                elif name in free and not reference:
                    low, high = bounds.get(key, bounds.get(name, BOUNDS[name]))
                    searched.append(FreeParameter(material, name, float(low), float(high)))
                else:
                    values[name] = float(start.get(key, REFERENCE_E if reference else STARTING[name]))
            fixed[material] = values
        unused = set(start) - {f"{m}.{n}" for m in materials for n in ("E", "nu", "eta")}
        if unused:
            raise ValueError(f"starting values {sorted(unused)} name no parameter of the {model} model "
                             f"(materials {materials})")
        geometric = ([(FIBRE, "gamma"), (FIBRE, "alpha")] if "fibre" in free else []) + \
                    ([(f"plate{i + 1}", "offset") for i in range(plates)] if "offset" in free else [])
        for owner, name in geometric:
            low, high = bounds.get(f"{owner}.{name}", bounds.get(name, GEOMETRY_BOUNDS[name]))
            searched.append(FreeParameter(owner, name, float(low), float(high)))
        return cls(model, names, searched, fixed, fibre, plates)

    def start(self) -> np.ndarray:
        """The unit position an optimisation starts from by default: the middle of each
        material parameter's range, the given fibre direction's angles (clipped to their
        bounds), zero plate offsets (clipped)."""
        gamma, alpha = fibre_angles(self.fibre)
        base = {"gamma": gamma, "alpha": alpha, "offset": 0.0}
        return np.array([float(np.clip(p.to_unit(base[p.name]), 0.0, 1.0)) if p.geometric else 0.5
                         for p in self.free])

    def values(self, z) -> dict[str, float]:
        """{"tissue.name": value} of the free parameters at unit position ``z`` (d,)."""
        z = np.asarray(z, float).reshape(-1)
        if z.shape != (self.dimension,):
            raise ValueError(f"a position in this space has {self.dimension} coordinates, not {z.size}")
        return {p.key: float(p.from_unit(zi)) for p, zi in zip(self.free, z)}

    def unit(self, values: dict[str, float]) -> np.ndarray:
        """The unit position of free-parameter ``values`` ({"tissue.name": value}, every free key)."""
        missing = set(self.keys) - set(values)
        if missing:
            raise ValueError(f"values needed for {sorted(missing)}")
        return np.array([float(p.to_unit(values[p.key])) for p in self.free])

    def _searched(self, z) -> list[tuple[FreeParameter, float]]:
        """Each free parameter with its value at unit position ``z``."""
        return list(zip(self.free, self.values(z).values()))

    def materials(self, z) -> dict[str, dict[str, float]]:
        """Every material's {"E", "nu", "eta"} at unit position ``z``."""
        table = {name: dict(values) for name, values in self.fixed.items()}
        for p, value in self._searched(z):
            if not p.geometric:
                table[p.tissue][p.name] = value
        return table

    def fibre_at(self, z) -> np.ndarray:
        """The unit fibre direction (LPS) at unit position ``z``: :attr:`fibre`, turned to the
        free angles' values where they are free."""
        free = {p.name: v for p, v in self._searched(z) if p.tissue == FIBRE}
        if not free:
            return np.asarray(self.fibre, float)
        angles = {**dict(zip(("gamma", "alpha"), fibre_angles(self.fibre))), **free}
        return fibre_direction(angles["gamma"], angles["alpha"])

    def plate_offsets(self, z) -> np.ndarray:
        """The plates' offsets (mm, along each normal, positive towards the tissue) at ``z``."""
        offsets = np.zeros(self.plates)
        for p, value in self._searched(z):
            if p.name == "offset":
                offsets[int(p.tissue[5:]) - 1] = value
        return offsets

    def geometry(self, z) -> dict:
        """The free geometry at ``z`` for results files: {"fibre": [x, y, z] (LPS)} where the
        fibre angles are free, {"plate_offsets_mm": [...]} where plate offsets are."""
        out = {}
        if any(p.tissue == FIBRE for p in self.free):
            out["fibre"] = [float(v) for v in self.fibre_at(z)]
        if any(p.name == "offset" for p in self.free):
            out["plate_offsets_mm"] = [float(v) for v in self.plate_offsets(z)]
        return out

    def element_materials(self, z, tissue: np.ndarray) -> ElementMaterials:
        """Per-element materials at ``z`` for element tissue labels ``tissue`` (M,)."""
        table = self.materials(z)
        fibre = self.fibre_at(z)
        tissue = np.asarray(tissue).astype(int)
        by_label = {}
        for label in labels_present(tissue):
            name = labels.tissue(label).name
            if name not in self.tissues:
                raise ValueError(f"the mesh holds {name}, which the parameter space does not know")
            values = table[HOMOGENEOUS if self.homogeneous else name]
            by_label[label] = Material(E=values["E"], nu=values["nu"], eta=values["eta"], fibre=fibre)
        return ElementMaterials.from_tissues(tissue, by_label)

    def to_dict(self) -> dict:
        return {"model": self.model, "tissues": self.tissues, "fibre": list(self.fibre),
                "free": [{"tissue": p.tissue, "name": p.name, "lower": p.lower, "upper": p.upper} for p in self.free],
                "fixed": self.fixed, **({"plates": self.plates} if self.plates else {})}

    @classmethod
    def from_dict(cls, data: dict) -> "ParameterSpace":
        return cls(data["model"], list(data["tissues"]), [FreeParameter(**p) for p in data["free"]],
                   {k: dict(v) for k, v in data["fixed"].items()}, tuple(data["fibre"]), int(data.get("plates", 0)))
