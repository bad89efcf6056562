"""What a candidate effect is: its parameters (units, range, the value at which it is off, the
step of its sensitivity) and how it changes a model variant. The fitted model is the nested
case: every effect at its off values changes nothing.

An effect's :meth:`Effect.apply` takes the variant of the current model and the effect's
parameter values and returns the changed variant; :meth:`Effect.unavailable` says why an effect
cannot apply to a fit (friction without plates, anisotropy in an anisotropic fit, ...), and the
diagnosis reports that reason instead of testing it.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class EffectParameter:
    """One parameter of an effect: ``name``, ``unit``, the ``off`` value (the fitted model),
    the range [``lower``, ``upper``] a refit may search, and the ``step`` of its secant
    sensitivity (a realistic size, so that effects that switch on abruptly - friction's stick
    and slip, a sliding chest wall - show their real signature rather than a tangent at zero)."""

    name: str
    unit: str
    off: float
    lower: float
    upper: float
    step: float
    description: str = ""

    def __post_init__(self) -> None:
        if not self.lower <= self.off <= self.upper or not self.lower < self.upper:
            raise ValueError(f"{self.name}: need lower <= off <= upper and lower < upper")
        if not self.step > 0:
            raise ValueError(f"{self.name}: the sensitivity step must be positive")

    def stepped(self, value: float) -> float:
        """``value`` moved by the step, towards the upper bound unless that would leave the range."""
        return value + self.step if value + self.step <= self.upper else value - self.step


class Effect(ABC):
    """A candidate physical effect the fitted model may be missing (subclass per effect: one file
    each in this package). ``name``: identifier (command line, JSON); ``title``: words for
    reports; ``acts_in``: where in the breast it acts; ``parameters``; ``own_model``: whether it
    changes the loading beyond materials and plates (then its variants are solved apart from the
    batch); ``order``: effects are applied in increasing order (the gravity pre-stress last: it
    is computed for the model with every other effect in place)."""

    name = ""
    title = ""
    acts_in = ""
    parameters: tuple[EffectParameter, ...] = ()
    own_model = False
    order = 0

    @property
    def off(self) -> np.ndarray:
        return np.array([p.off for p in self.parameters])

    @property
    def lower(self) -> np.ndarray:
        return np.array([p.lower for p in self.parameters])

    @property
    def upper(self) -> np.ndarray:
        return np.array([p.upper for p in self.parameters])

    def unavailable(self, fitted) -> str | None:
        """Why this effect cannot apply to ``fitted`` (a :class:`~BreastBiomechLib.discrepancy.fitted.FittedCase`),
        or None when it can."""
        return None

    def unavailable_at(self, fitted, added) -> str | None:
        """Why this effect cannot apply to ``fitted`` with the effects ``added`` in earlier rounds
        ({name: (effect, values)}, :attr:`~BreastBiomechLib.discrepancy.state.ModelState.added`),
        or None: :meth:`unavailable`, unless the effect refines one that must be added first."""
        return self.unavailable(fitted)

    @abstractmethod
    def apply(self, variant, values: np.ndarray, fitted):
        """The ``variant`` with this effect at parameter ``values`` (one per parameter)."""

    def column_key(self, j: int):
        """An identity of parameter ``j``'s secant model that another effect's parameter shares
        (the same model, built by the same code), so that the sensitivities solve it once; None
        (the default) where it is this effect's own."""
        return None

    def describe(self, values) -> str:
        """The values in words, e.g. "mu 0.42"."""
        return ", ".join(f"{p.name} {v:.3g}{' ' + p.unit if p.unit else ''}" for p, v in zip(self.parameters, values))


def switched_on(added, name: str) -> bool:
    """Whether effect ``name`` is among the effects ``added`` ({name: (effect, values)}) with its
    first parameter above zero (friction's mu, gravity's s): what a refinement of it needs."""
    entry = added.get(name)
    return entry is not None and float(np.asarray(entry[1])[0]) > 0
