"""The material parameters an optimisation searches (seed section 2.4 and section 3.2): per tissue
Young's modulus E, Poisson's ratio nu and the fibre stiffness eta of the transversely isotropic
neo-Hookean model, with the seed's bounds; the four model variants of the seed's Tables 2 and 3.

Units: E and eta in Pa, nu dimensionless, fibre directions unit vectors (LPS). Fat is the
reference: the plates prescribe displacements, so only stiffness ratios shape the deformation,
and fat's E stays at E_f = 10 kPa (the seed's choice). Optimisers work in the unit cube: each
free parameter maps [0, 1] onto its bounds on a log scale for E and eta (they span decades) and
on log(0.5 - nu) for nu (the bulk modulus, 1 / (1 - 2 nu), is what nu controls near 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from BreastBiomechLib import labels
from BreastBiomechLib.solver.materials import ElementMaterials, Material

MODELS = ("iso-homo", "iso-hetero", "aniso-homo", "aniso-hetero")
BOUNDS = {"E": (100.0, 1e6), "nu": (0.45, 0.4999), "eta": (1.0, 1e6)}  # the seed's section 3.2
REFERENCE_E = 10e3  # E_f, fat's Young's modulus (Pa)
HOMOGENEOUS = "breast"  # the one material of a homogeneous model
STARTING = {"E": REFERENCE_E, "nu": 0.49, "eta": 1e3}  # values of parameters that are not free


@dataclass(frozen=True)
class FreeParameter:
    """One searched parameter: ``tissue`` (a tissue name, or "breast" for the one material of a
    homogeneous model), ``name`` ("E", "nu" or "eta") and its bounds."""

    tissue: str
    name: str
    lower: float
    upper: float

    def __post_init__(self) -> None:
        if self.name not in BOUNDS:
            raise ValueError(f"{self.key}: free parameters are {sorted(BOUNDS)}")
        if not 0 < self.lower < self.upper:
            raise ValueError(f"{self.key}: the bounds must satisfy 0 < lower < upper, not [{self.lower}, {self.upper}]")
        if self.name == "nu" and self.upper >= 0.5:
            raise ValueError(f"{self.key}: Poisson's ratio must stay below 0.5")

    @property
    def key(self) -> str:
        return f"{self.tissue}.{self.name}"

    def _scaled(self, value):
        return np.log(0.5 - np.asarray(value, float)) if self.name == "nu" else np.log(np.asarray(value, float))

    def to_unit(self, value) -> np.ndarray:
        """The position of ``value`` in [0, 1] (0 at the lower bound)."""
        low, high = self._scaled(self.lower), self._scaled(self.upper)
        return (self._scaled(value) - low) / (high - low)

    def from_unit(self, z) -> np.ndarray:
        """The value at unit position ``z`` (clipped to [0, 1])."""
        low, high = self._scaled(self.lower), self._scaled(self.upper)
        scaled = low + np.clip(np.asarray(z, float), 0.0, 1.0) * (high - low)
        return 0.5 - np.exp(scaled) if self.name == "nu" else np.exp(scaled)


@dataclass
class ParameterSpace:
    """What an optimisation searches: the ``free`` parameters and the ``fixed`` values of every
    material ({tissue or "breast": {"E", "nu", "eta"}}), for a model variant of :data:`MODELS`
    on a mesh holding ``tissues`` (names). ``fibre``: the unit fibre direction (LPS) of the
    anisotropic variants."""

    model: str
    tissues: list[str]
    free: list[FreeParameter]
    fixed: dict[str, dict[str, float]]
    fibre: tuple[float, float, float] = (0.0, 0.0, 1.0)

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
            if p.tissue not in materials:
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
                  fibre=(0.0, 0.0, 1.0), start: dict | None = None) -> "ParameterSpace":
        """The seed's variant ``model`` on a mesh with ``tissues`` (names or labels): each
        material's parameters named in ``free`` are searched within the seed's bounds (or
        ``bounds``: {"E" | "nu" | "eta" or "tissue.name": (lower, upper)}), except fat's E (the
        reference) and, for isotropic variants, eta (zero). Parameters not free keep ``start``
        ({"tissue.name": value}) or the starting values (E_f, nu 0.49, eta 1 kPa)."""
        if model not in MODELS:
            raise ValueError(f"unknown model {model!r}; choose one of {MODELS}")
        unknown = set(free) - set(BOUNDS)
        if unknown:
            raise ValueError(f"unknown free parameters {sorted(unknown)}; choose among {sorted(BOUNDS)}")
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
        return cls(model, names, searched, fixed, fibre)

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

    def materials(self, z) -> dict[str, dict[str, float]]:
        """Every material's {"E", "nu", "eta"} at unit position ``z``."""
        table = {name: dict(values) for name, values in self.fixed.items()}
        for key, value in self.values(z).items():
            material, name = key.split(".")
            table[material][name] = value
        return table

    def element_materials(self, z, tissue: np.ndarray) -> ElementMaterials:
        """Per-element materials at ``z`` for element tissue labels ``tissue`` (M,)."""
        table = self.materials(z)
        by_label = {}
        for label in np.unique(np.asarray(tissue).astype(int)).tolist():
            name = labels.tissue(label).name
            if name not in self.tissues:
                raise ValueError(f"the mesh holds {name}, which the parameter space does not know")
            values = table[HOMOGENEOUS if self.homogeneous else name]
            by_label[label] = Material(E=values["E"], nu=values["nu"], eta=values["eta"], fibre=self.fibre)
        return ElementMaterials.from_tissues(np.asarray(tissue).astype(int), by_label)

    def to_dict(self) -> dict:
        return {"model": self.model, "tissues": self.tissues, "fibre": list(self.fibre),
                "free": [{"tissue": p.tissue, "name": p.name, "lower": p.lower, "upper": p.upper} for p in self.free],
                "fixed": self.fixed}

    @classmethod
    def from_dict(cls, data: dict) -> "ParameterSpace":
        return cls(data["model"], list(data["tissues"]), [FreeParameter(**p) for p in data["free"]],
                   {k: dict(v) for k, v in data["fixed"].items()}, tuple(data["fibre"]))
