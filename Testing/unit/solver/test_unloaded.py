"""The unloaded reference state (solver.unloaded) on a TetGen breast (2.5k tets, E = 3 kPa, prone
gravity, warp's CPU device): the estimate re-loads to the imaged shape, a pre-stressed model rests
there, a compression from it differs from today's model in the direction the physics says, a
change of posture moves the breast the other way, and bad input is refused."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from BreastBiomechLib.solver import DynamicRelaxation, Material, solve
from BreastBiomechLib.solver.unloaded import prestressed_model, unloaded_shape

PRONE = np.array([0.0, -9.81, 0.0])  # LPS: anterior, towards the table's opening in a prone MR


@pytest.fixture(scope="module")
def breast():
    from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression

    model = hemi_ellipsoid_compression(10.0, smooth=True, material=Material(E=3e3, nu=0.49))
    steps = []
    unloaded = unloaded_shape(model, PRONE, tolerance_mm=0.02, progress=lambda i, r: steps.append((i, r)))
    return model, unloaded, steps


def _relaxed(model):
    solution = solve(model, device="cpu", relaxation=DynamicRelaxation())
    assert solution.ok, solution.message
    return model.mesh.nodes + solution.displacement


def test_the_unloaded_shape_reloads_to_the_imaged_one(breast):
    model, unloaded, steps = breast
    assert unloaded.residual_mm <= 0.02 and unloaded.iterations == len(unloaded.history) == len(steps)
    assert all(b < a for a, b in zip(unloaded.history, unloaded.history[1:]))  # converging
    sag = np.linalg.norm(unloaded.loaded_displacement, axis=1).max()
    assert sag > 3.0  # mm: gravity matters for this soft breast
    # the stress-free breast lies posterior to the imaged one (gravity pulled it anteriorly)
    assert (unloaded.nodes - model.mesh.nodes)[:, 1].mean() > 0.5
    # independently re-loaded (a fresh gravity-only solve of the stress-free mesh, tighter tolerance)
    rested = prestressed_model(replace(model, loading=replace(model.loading, plates=[])), unloaded)
    reloaded = _relaxed(replace(rested, prestate=None, loading=replace(rested.loading, gravity=PRONE)))
    assert np.linalg.norm(reloaded - model.mesh.nodes, axis=1).max() < 0.1
    # started pre-stressed with gravity kept on and nothing else, it stays where it was imaged
    assert np.linalg.norm(_relaxed(rested) - model.mesh.nodes, axis=1).max() < 0.1


def test_a_prestressed_compression_differs_in_the_direction_the_physics_says(breast):
    """Taking the imaged prone shape as stress-free and adding gravity counts the sag twice: that
    breast ends further along gravity (anterior) than the pre-stressed one, by a sizeable part
    of the sag. Today's model (no gravity at all) differs from the pre-stressed one too."""
    model, unloaded, _ = breast
    prestressed = _relaxed(prestressed_model(model, unloaded))
    twice = _relaxed(replace(model, loading=replace(model.loading, gravity=PRONE)))
    today = _relaxed(model)
    sag = np.linalg.norm(unloaded.loaded_displacement, axis=1).mean()
    assert (prestressed - twice)[:, 1].mean() > 0.5 * sag
    assert np.abs(prestressed - today).max() > 0.2


def test_a_change_of_posture_moves_the_breast_against_the_old_gravity(breast):
    """Turned from prone to supine (gravity posterior) with no plates: the breast moves
    posteriorly past its stress-free shape."""
    model, unloaded, _ = breast
    supine = _relaxed(prestressed_model(replace(model, loading=replace(model.loading, plates=[])), unloaded, -PRONE))
    shift = (supine - model.mesh.nodes)[:, 1].mean()
    assert shift > 1.5 * (unloaded.nodes - model.mesh.nodes)[:, 1].mean() > 0


def test_bad_unloaded_state_input_is_refused(breast):
    model, unloaded, _ = breast
    with pytest.raises(ValueError, match="finite"):
        unloaded_shape(model, [0, np.nan, 0])
    with pytest.raises(ValueError, match="would fall"):
        unloaded_shape(replace(model, loading=replace(model.loading, constraints=[], plates=[])), PRONE)
    with pytest.raises(ValueError, match="pre-stressed"):
        solve(prestressed_model(model, unloaded), device="cpu", initial_displacement=np.zeros_like(model.mesh.nodes))
