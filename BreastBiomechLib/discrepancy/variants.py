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

A variant may start at a solved variant's equilibrium (``start``: a Gauss-Newton refinement's trial
steps, each near the current model): :mod:`~BreastBiomechLib.solver.warm`, the same equilibrium
within the relaxation's tolerance, mostly in fewer iterations; one that has not converged in twice
its start's iterations is solved again from rest. The diagnosis's sensitivities start every
variant at rest: on a CPU, where a batch costs the sum of its models' iterations, warm starts of
their variants saved 14-29 % on two cases and cost twice the time on a third (a plate offset's
variant oscillating at a contact for 50 000 iterations; docs/discrepancy.md, "Candidate effects").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from BreastBiomechLib.solver import DynamicRelaxation, Model
from BreastBiomechLib.solver.materials import ElementMaterials
from BreastBiomechLib.solver.model import Plate
from BreastBiomechLib.solver.run_case import CaseVariant, run_variants
from BreastBiomechLib.solver.settings import SolverSettings
from BreastBiomechLib.solver.warm import WarmStart, started_plates


@dataclass
class Variant:
    """One model to solve: ``model`` (loading and mesh), ``materials`` per element, ``plates``
    (the model's plates in number and order, with their contact nodes); in a fit of several
    measured states this is the first state's, and ``others`` the same model in each further
    state, solved with it. ``compressed_gravity``: the compressed scan's gravity (m/s^2, LPS)
    where an effect turned the recorded posture (None: the fitted case's), for the gravity
    pre-stress to load with."""

    model: Model
    materials: ElementMaterials
    plates: list[Plate]
    others: list["Variant"] = field(default_factory=list)
    compressed_gravity: np.ndarray | None = None


@dataclass
class Outcome:
    """A variant's solve: ``displacement`` (N, 3) mm from the mesh as imaged, ``status`` and
    ``message`` of the solver (``ok`` when it completed), and the forward solves it took
    (``attempts``: more than 1 where it was solved again with a slower load); ``starts``: for
    each model it was solved with that completed (the first state's and each further state's),
    the warm start at its equilibrium (id of the model -> (model, start))."""

    displacement: np.ndarray
    status: str
    message: str
    attempts: int = 1
    starts: dict[int, tuple[Model, WarmStart]] = field(default_factory=dict, repr=False)

    @property
    def ok(self) -> bool:
        return self.status == "completed"


def solve_variants(variants: list[Variant], imaged_nodes: np.ndarray, relaxation: DynamicRelaxation,
                   device=None, start: Outcome | None = None) -> list[Outcome]:
    """Solve every variant (one batched launch per distinct ``model``) to static equilibrium by
    dynamic ``relaxation`` (:func:`~BreastBiomechLib.solver.run_case.run_variants`: a variant that
    inverts an element is solved again alone with a slower load); the outcomes in the variants'
    order. A variant with :attr:`Variant.others` is solved in every state: its outcome's
    displacement is the states' stacked (first state first), its status the first failed state's.
    ``start``: a solved variant's outcome; the variants of a model it was solved with, whose
    plates differ from that solve's in travel only and have no friction (the warm start's
    conditions, :func:`~BreastBiomechLib.solver.warm.started_plates`), start at its equilibrium,
    in a launch of their own, and those of them that do not converge there
    (:meth:`~BreastBiomechLib.solver.warm.WarmStart.bounded`) are solved again from rest with the
    rest (their ``attempts`` count both)."""
    flat = [(i, part) for i, variant in enumerate(variants) for part in (variant, *variant.others)]
    solved: list[Outcome | None] = [None] * len(flat)
    groups: dict[int, list[int]] = {}
    for k, (_, part) in enumerate(flat):
        groups.setdefault(id(part.model), []).append(k)
    settings = SolverSettings(method="relaxation", device=device, relaxation=relaxation)
    for members in groups.values():
        model = flat[members[0]][1].model
        warm = _warm_start(start, model)
        warmed = [k for k in members if warm is not None and _starts_warm(model, warm, flat[k][1].plates)]
        cold = [k for k in members if k not in warmed]
        for launch, launch_start in ((warmed, warm), (cold, None)):
            if not launch:
                continue
            results = run_variants(model, [CaseVariant(flat[k][1].materials, flat[k][1].plates) for k in launch],
                                   settings, imaged_nodes=imaged_nodes, warm_start=launch_start)
            for k, result in zip(launch, results):
                solution, plates = result.solution, flat[k][1].plates
                if launch_start is not None and solution.status == "not converged":
                    cold.append(k)  # solved again from rest, below
                    solved[k] = Outcome(result.displacement, solution.status, solution.message, solution.attempts)
                    continue
                starts = {} if not solution.ok else {id(model): (model, WarmStart.from_solution(
                    solution, np.array([p.displacement for p in plates]).reshape(-1, 3), launch_start))}
                tried = solved[k].attempts if solved[k] is not None else 0
                solved[k] = Outcome(result.displacement, solution.status, solution.message,
                                    solution.attempts + tried, starts)
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
                                failed.message if failed else parts[0].message, sum(p.attempts for p in parts),
                                {key: value for p in parts for key, value in p.starts.items()}))
    return outcomes


def _warm_start(start: Outcome | None, model: Model) -> WarmStart | None:
    """``start``'s warm start for ``model`` (None: none, or it was not solved with that model)."""
    if start is None or id(model) not in start.starts:
        return None
    owner, warm = start.starts[id(model)]
    return warm if owner is model else None


def _starts_warm(model: Model, warm: WarmStart, plates: list[Plate]) -> bool:
    """Whether a variant of ``model`` with ``plates`` may start at ``warm``: the plates differ
    from the start's in travel only and have no friction."""
    try:
        started_plates(model, warm, [plates])
    except ValueError:
        return False
    return True
