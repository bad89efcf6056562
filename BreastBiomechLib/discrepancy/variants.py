"""A model variant (one forward solve of the diagnosis) and the batched solve of many.

A :class:`Variant` is what a solve needs beyond the mesh: the ``model`` (mesh, constraints,
supports, gravity and reference state; its own materials and plates are not used), the
per-element ``materials`` and the ``plates``. Variants that share one ``model`` object are
solved in one batched launch (materials, plate poses, travel and friction may differ between
them); an effect that changes the loading (gravity pre-stress, the chest-wall support) makes a
model of its own. Displacements come back from the mesh as imaged (LPS mm), also for a
pre-stressed model whose mesh is its unloaded shape. A fit of several measured states solves each
variant in every state (:attr:`Variant.others`): its displacement is the states' one after the
other (:meth:`~BreastBiomechLib.discrepancy.fitted.FittedCase.split`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from BreastBiomechLib.solver import DynamicRelaxation, Model
from BreastBiomechLib.solver.materials import ElementMaterials
from BreastBiomechLib.solver.model import Plate
from BreastBiomechLib.solver.run_case import CaseVariant, run_variants
from BreastBiomechLib.solver.settings import SolverSettings


@dataclass
class Variant:
    """One model to solve: ``model`` (loading and mesh), ``materials`` per element, ``plates``
    (the model's plates in number and order, with their contact nodes); in a fit of several
    measured states this is the first state's, and ``others`` the same model in each further
    state, solved with it."""

    model: Model
    materials: ElementMaterials
    plates: list[Plate]
    others: list["Variant"] = field(default_factory=list)


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
    inverts an element is solved again alone with a slower load); the outcomes in the variants'
    order. A variant with :attr:`Variant.others` is solved in every state: its outcome's
    displacement is the states' stacked (first state first), its status the first failed state's."""
    flat = [(i, part) for i, variant in enumerate(variants) for part in (variant, *variant.others)]
    solved: list[Outcome | None] = [None] * len(flat)
    groups: dict[int, list[int]] = {}
    for k, (_, part) in enumerate(flat):
        groups.setdefault(id(part.model), []).append(k)
    settings = SolverSettings(method="relaxation", device=device, relaxation=relaxation)
    for members in groups.values():
        results = run_variants(flat[members[0]][1].model,
                               [CaseVariant(flat[k][1].materials, flat[k][1].plates) for k in members], settings,
                               imaged_nodes=imaged_nodes)
        for k, result in zip(members, results):
            solved[k] = Outcome(result.displacement, result.solution.status, result.solution.message,
                                result.solution.attempts)
    parts_of: dict[int, list[Outcome]] = {}
    for (owner, _), outcome in zip(flat, solved):
        parts_of.setdefault(owner, []).append(outcome)
    outcomes = []
    for i in range(len(variants)):
        parts = parts_of[i]
        if len(parts) == 1:
            outcomes.append(parts[0])
            continue
        failed = next((p for p in parts if not p.ok), None)
        outcomes.append(Outcome(np.concatenate([p.displacement for p in parts]),
                                failed.status if failed else parts[0].status,
                                failed.message if failed else parts[0].message, sum(p.attempts for p in parts)))
    return outcomes
