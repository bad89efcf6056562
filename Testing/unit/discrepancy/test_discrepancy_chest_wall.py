"""The chest-wall candidate effect: a hold along the chest wall, nested exactly in the fitted (the
seed's, free-sliding) chest wall."""

from __future__ import annotations

import pytest


def test_the_hold_is_nested_in_the_fitted_chest_wall_and_grows_with_h():
    """h = 0 is the fit's chest wall exactly (no spring); h > 0 adds springs along the chest wall
    only (free across it, where the fit's anterior-posterior hold stays), stiffer as h grows."""
    from BreastBiomechLib.discrepancy.effects.chest_wall import REFERENCE_STIFFNESS, hold_stiffness
    from BreastBiomechLib.solver.model import SurfaceSupport

    assert hold_stiffness(0.0) == 0.0
    assert hold_stiffness(0.5) == pytest.approx(REFERENCE_STIFFNESS)
    assert hold_stiffness(0.9) == pytest.approx(9 * REFERENCE_STIFFNESS)
    springs = SurfaceSupport([0, 1], [[0, 1, 0], [0, 1, 0]], [1.0, 1.0], "elastic", 0.0, 340.0)
    assert springs.normal_stiffness == 0.0 and springs.tangential_stiffness == 340.0
    with pytest.raises(ValueError, match="needs a spring"):
        SurfaceSupport([0], [[0, 1, 0]], [1.0], "elastic", 0.0, 0.0)
