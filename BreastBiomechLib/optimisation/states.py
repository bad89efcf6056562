"""A fit of several measured states of one breast at once: one set of material parameters, each
state its own plates, measured image and landmarks (:mod:`BreastBiomechLib.io.case_layout`'s
``compressed/`` and ``states/<name>/``). Each state is a
:class:`~BreastBiomechLib.optimisation.forward.FittingProblem` on the same fitting mesh and
parameter space; a parameter set's objective is the mean of the states' objectives (each -NMI,
or a landmark or surface distance, alike in scale from state to state), and it fails where any
state's solve fails.

Frames and units as in :mod:`BreastBiomechLib.optimisation.forward`: LPS millimetres, the
fitting mesh as imaged (undeformed).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from BreastBiomechLib.optimisation.forward import Evaluation, FittingProblem


@dataclass
class StateSolutions:
    """The solutions (:class:`~BreastBiomechLib.solver.Solution`) of one parameter set in each
    measured state, by state name in the fit's order (the first state first)."""

    solutions: dict

    @property
    def ok(self) -> bool:
        return all(s.ok for s in self.solutions.values())

    @property
    def message(self) -> str:
        return "; ".join(f"state {name}: {s.message}" for name, s in self.solutions.items() if not s.ok)


class JointProblem:
    """Evaluates parameter sets on every measured state of a case: ``problems`` maps each state's
    name to its :class:`FittingProblem` (the first state first; one fitting mesh, parameter space
    and objective for all). Offers what :func:`~BreastBiomechLib.optimisation.run.optimise`
    and :func:`~BreastBiomechLib.optimisation.run.solve_best` use of a problem."""

    def __init__(self, problems: dict[str, FittingProblem]):
        if len(problems) < 2:
            raise ValueError("a joint fit needs at least two measured states; fit one state with its FittingProblem")
        first = next(iter(problems.values()))
        for name, problem in problems.items():
            if problem.mesh is not first.mesh or problem.space.to_dict() != first.space.to_dict():
                raise ValueError(f"state {name!r}: every state of a joint fit shares the fitting mesh and the "
                                 "parameter space")
            if problem.objective != first.objective:
                raise ValueError(f"state {name!r}: objective {problem.objective!r}, the first state's "
                                 f"{first.objective!r}: one objective for all states")
        if first.space.plates:
            raise ValueError("the plates' offsets are fitted per state's plates: a joint fit of several states "
                             "fits the materials only (leave 'offset' out of the free parameters)")
        self.problems = dict(problems)
        self.space = first.space
        self.objective = first.objective
        self.mesh = first.mesh

    @property
    def states(self) -> list[str]:
        return list(self.problems)

    @property
    def failed_objective(self) -> float:
        return next(iter(self.problems.values())).failed_objective

    def start_fit(self, folder: str | Path | None = None, recorded: list | None = None) -> None:
        """Each state's :meth:`FittingProblem.start_fit` (its warm starts kept in
        ``folder``/<state>)."""
        for name, problem in self.problems.items():
            problem.start_fit(None if folder is None else Path(folder) / name, recorded)

    def evaluate(self, positions) -> list[Evaluation]:
        """Evaluate unit positions (B, d) in every state (one batched solve per state): each
        evaluation's objective, NMI and NCC are the states' means, its landmark errors the mean
        and largest over every state's landmarks, its status the first failed state's (else
        completed), its iterations and seconds the states' sums; ``states`` keeps each state's
        own figures."""
        per_state = {name: problem.evaluate(positions) for name, problem in self.problems.items()}
        out = []
        for i in range(len(np.atleast_2d(positions))):
            rows = {name: evaluations[i] for name, evaluations in per_state.items()}
            first = next(iter(rows.values()))
            failed = [(name, e) for name, e in rows.items() if e.status != "completed"]
            out.append(Evaluation(
                first.z, first.values,
                self.failed_objective if failed else float(np.mean([e.objective for e in rows.values()])),
                _mean(e.nmi for e in rows.values()), _mean(e.ncc for e in rows.values()),
                _mean(e.landmark_mean_mm for e in rows.values()),
                float(np.max([e.landmark_max_mm for e in rows.values()])),
                failed[0][1].status if failed else "completed",
                int(sum(e.iterations for e in rows.values())), round(sum(e.seconds for e in rows.values()), 3),
                _mean(e.surface_mm for e in rows.values()),
                "; ".join(f"state {name}: {e.message}" for name, e in failed),
                {name: {"objective": e.objective, "nmi": e.nmi, "landmark_mean_mm": e.landmark_mean_mm,
                        "status": e.status} for name, e in rows.items()}))
        return out

    def solve_alone(self, z) -> StateSolutions:
        """The solutions at one unit position ``z`` in every state, each solved by itself
        (:meth:`FittingProblem.solve_alone`)."""
        return StateSolutions({name: problem.solve_alone(z) for name, problem in self.problems.items()})


def _mean(values) -> float:
    """The mean of ``values`` (NaN where any is NaN, as where a state has no landmarks)."""
    return float(np.mean(list(values)))
