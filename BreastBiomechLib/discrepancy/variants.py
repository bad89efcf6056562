"""A model variant (one forward solve of the diagnosis) and the batched solve of many.

A :class:`Variant` is what a solve needs beyond the mesh: the ``model`` (mesh, constraints,
supports, gravity and reference state; its own materials and plates are not used), the
per-element ``materials`` and the ``plates``. Variants that share one ``model`` object are
solved in one batched launch (materials, plate poses, travel and friction may differ between
them); an effect that changes the loading (gravity pre-stress, the chest-wall support) makes a
model of its own. Displacements come back from the mesh as imaged (LPS mm), also for a
pre-stressed model whose mesh is its unloaded shape.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from BreastBiomechLib.solver import DynamicRelaxation, Model
from BreastBiomechLib.solver.materials import ElementMaterials
from BreastBiomechLib.solver.model import Plate
from BreastBiomechLib.solver.run_case import CaseVariant, run_variants
from BreastBiomechLib.solver.settings import SolverSettings


@dataclass
class Variant:
    """One model to solve: ``model`` (loading and mesh), ``materials`` per element, ``plates``
    (the model's plates in number and order, with their contact nodes)."""

    model: Model
    materials: ElementMaterials
    plates: list[Plate]


@dataclass
class Outcome:
    """A variant's solve: ``displacement`` (N, 3) mm from the mesh as imaged, ``status`` and
    ``message`` of the solver (``ok`` when it completed), and the forward solves it took
    (``attempts``: more than 1 where it was solved again with a slower load)."""

    displacement: np.ndarray
    status: str
    message: str
    attempts: int = 1

    @property
    def ok(self) -> bool:
        return self.status == "completed"


def solve_variants(variants: list[Variant], imaged_nodes: np.ndarray, relaxation: DynamicRelaxation,
                   device=None) -> list[Outcome]:
    """Solve every variant (one batched launch per distinct ``model``) to static equilibrium by
    dynamic ``relaxation`` (:func:`~BreastBiomechLib.solver.run_case.run_variants`: a variant that
    inverts an element is solved again alone with a slower load); the outcomes in the variants' order."""
    outcomes: list[Outcome | None] = [None] * len(variants)
    groups: dict[int, list[int]] = {}
    for i, variant in enumerate(variants):
        groups.setdefault(id(variant.model), []).append(i)
    settings = SolverSettings(method="relaxation", device=device, relaxation=relaxation)
    for members in groups.values():
        results = run_variants(variants[members[0]].model,
                               [CaseVariant(variants[i].materials, variants[i].plates) for i in members], settings,
                               imaged_nodes=imaged_nodes)
        for i, result in zip(members, results):
            outcomes[i] = Outcome(result.displacement, result.solution.status, result.solution.message,
                                  result.solution.attempts)
    return outcomes
