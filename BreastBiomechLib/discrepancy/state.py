"""The model of a diagnosis round: the fit's parameters plus the effects added so far, and the
variants it solves (the model itself, or it with fit parameters or effect parameters changed).

Parameters are addressed by keys: the fit's free parameters by their space key
("glandular.E", ...) in unit coordinates of the fit's space; an effect's parameters as
"<effect>:<index>" in the effect's own units.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from BreastBiomechLib.discrepancy.effects import Effect
from BreastBiomechLib.discrepancy.fitted import FittedCase
from BreastBiomechLib.discrepancy.variants import Variant

FIT_STEP = 0.02  # finite-difference step of the fit's parameters, in unit coordinates (E: x1.2)


@dataclass
class ModelState:
    """``fitted``: the case and its fit; ``z``: the fit's parameters (unit coordinates, possibly
    refitted); ``added``: the effects added so far with their values (applied in their order)."""

    fitted: FittedCase
    z: np.ndarray
    added: dict[str, tuple[Effect, np.ndarray]] = field(default_factory=dict)

    def variant(self, z=None, values: dict[str, np.ndarray] | None = None) -> Variant:
        """The variant at fit parameters ``z`` (default :attr:`z`) with the added effects at their
        values, overridden or extended by ``values`` ({effect name: (Effect, its values)}); in a
        fit of several measured states, the first state's, with the same model in each further
        state (its plates and posture) in :attr:`Variant.others`."""
        z = self.z if z is None else np.asarray(z, float)
        chosen = {name: (effect, v) for name, (effect, v) in self.added.items()}
        for name, (effect, v) in (values or {}).items():
            chosen[name] = (effect, np.asarray(v, float))
        ordered = sorted(chosen.values(), key=lambda item: item[0].order)
        first, *further = [_variant_in(state, z, ordered) for state in self.fitted.states]
        first.others = further
        return first

    def with_effect(self, effect: Effect, values, z=None) -> "ModelState":
        """This state with ``effect`` added (or changed) at ``values`` and the fit's parameters at
        ``z`` (default unchanged)."""
        added = dict(self.added)
        added[effect.name] = (effect, np.asarray(values, float))
        return ModelState(self.fitted, self.z if z is None else np.asarray(z, float), added)

    def nuisance(self) -> list[tuple[str, float, float, float]]:
        """The parameters a diagnosis takes as fitted (the fit's free ones, then the added effects'):
        (key, value, lower, upper) each, unit coordinates for the fit's, effect units for the others."""
        out = [(key, float(v), 0.0, 1.0) for key, v in zip(self.fitted.space.keys, self.z)]
        for name, (effect, values) in self.added.items():
            out += [(f"{name}:{i}", float(v), p.lower, p.upper) for i, (p, v) in enumerate(zip(effect.parameters, values))]
        return out

    def moved(self, key: str, value: float) -> tuple[np.ndarray, dict]:
        """(z, effect values) with the nuisance parameter ``key`` at ``value``."""
        if ":" not in key:
            z = self.z.copy()
            z[self.fitted.space.keys.index(key)] = value
            return z, {}
        name, index = key.split(":")
        effect, values = self.added[name]
        values = values.copy()
        values[int(index)] = value
        return self.z, {name: (effect, values)}

    def with_nuisance(self, values) -> "ModelState":
        """This state with every nuisance parameter (the order of :meth:`nuisance`) at ``values``."""
        values = np.asarray(values, float)
        d = len(self.z)
        added, at = {}, d
        for name, (effect, old) in self.added.items():
            added[name] = (effect, values[at:at + len(old)].copy())
            at += len(old)
        return ModelState(self.fitted, values[:d].copy(), added)

    def to_dict(self) -> dict:
        return {"z": [float(v) for v in self.z], "fit_values": self.fitted.space.values(self.z),
                "added": {name: [float(v) for v in values] for name, (_, values) in self.added.items()}}


def _variant_in(fitted: FittedCase, z: np.ndarray, effects: list[tuple[Effect, np.ndarray]]) -> Variant:
    """The variant of measured state ``fitted`` at fit parameters ``z`` with ``effects`` ((Effect,
    values), in the order applied)."""
    plates = fitted.plates
    offsets = fitted.problem.plate_displacements(z)
    if offsets is not None:
        plates = [replace(p, displacement=d) for p, d in zip(plates, offsets)]
    variant = Variant(fitted.model, fitted.space.element_materials(z, fitted.tissue), plates)
    for effect, v in effects:
        variant = effect.apply(variant, v, fitted)
    return variant
