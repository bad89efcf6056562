"""A fit's warm starts (optimisation/warm_starts.py): each batch starts at the best completed
evaluation's equilibrium, reaches the cold solves' objectives in fewer iterations, and a
cancelled fit resumed from its folder evaluates every position exactly as an uninterrupted one."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from BreastBiomechLib.optimisation import FittingProblem, ParameterSpace, optimise
from BreastBiomechLib.optimisation.synthetic import measured_at, synthetic_case
from BreastBiomechLib.solver import DynamicRelaxation

RELAXATION = DynamicRelaxation(load_iterations=400, tolerance_mm=0.002)


@pytest.fixture(scope="module")
def case():
    """The small synthetic breast and its image measured at fat nu 0.49, glandular E 30 kPa, nu 0.48."""
    case = synthetic_case((40.0, 35.0, 40.0), element_mm=6.0, voxel_mm=(2.0, 2.0, 2.0))
    space = ParameterSpace.for_model("iso-hetero", ["fat", "glandular"], free=("E", "nu"))
    measured = measured_at(case, space, {"fat.nu": 0.49, "glandular.E": 30e3, "glandular.nu": 0.48}, RELAXATION,
                           device="cpu")
    return case, space, measured


def problem_of(case, warm_starts=True):
    case, space, measured = case
    return FittingProblem(space, case.mesh, case.undeformed, measured, case.planes, relaxation=RELAXATION,
                          device="cpu", warm_starts=warm_starts)


def test_warm_started_batches_reach_the_cold_objectives_in_fewer_iterations(case):
    warm, cold = problem_of(case), problem_of(case, warm_starts=False)
    rng = np.random.default_rng(3)
    first = rng.uniform(0.3, 0.7, (3, 3))
    warm.start_fit()
    warm.evaluate(first)
    assert warm.warm_start is not None  # the best of the first batch
    near = np.clip(first[0] + rng.normal(0.0, 0.05, (4, 3)), 0.0, 1.0)
    from_start, from_rest = warm.evaluate(near), cold.evaluate(near)
    for w, c in zip(from_start, from_rest):
        assert w.status == c.status == "completed"
        assert w.objective == pytest.approx(c.objective, abs=2e-4)
    assert sum(w.iterations for w in from_start) < 0.9 * sum(c.iterations for c in from_rest)


def test_a_resumed_fit_evaluates_every_position_as_an_uninterrupted_one(case, tmp_path):
    problem = problem_of(case)
    whole = optimise(problem, "cmaes", budget=12, seed=2, population=4)
    calls = []

    def cancel_after_two_batches(done, budget, best, phase):
        calls.append(done)
        return len(calls) < 2

    optimise(problem, "cmaes", budget=12, seed=2, population=4, out_dir=tmp_path, progress=cancel_after_two_batches)
    starts = list((tmp_path / "warm_starts").glob("*.npz"))
    assert 1 <= len(starts) <= 2  # the current start and the one before it at most
    resumed = optimise(problem, "cmaes", budget=12, seed=2, population=4, out_dir=tmp_path, resume=True)
    assert resumed.replayed == 8
    assert [(e.z, e.objective, e.iterations) for e in resumed.evaluations] == \
        [(e.z, e.objective, e.iterations) for e in whole.evaluations]
    # the later batches did start warm: fewer iterations than the same positions solved cold
    later = whole.evaluations[8:]
    cold = problem_of(case, warm_starts=False).evaluate(np.array([e.z for e in later]))
    assert sum(e.iterations for e in later) < 0.9 * sum(e.iterations for e in cold)


def test_plate_friction_turns_warm_starts_off(case):
    problem = problem_of(case)
    problem.start_fit()
    problem.evaluate(np.full((1, 3), 0.5))
    assert problem.warm_start is not None
    problem.model.loading.plates = [replace(p, friction=0.3) for p in problem.model.loading.plates]
    assert problem.warm_start is None
