"""Compression plates placed on a mesh, and plates that start inside the tissue refused."""

from __future__ import annotations

import numpy as np
import pytest

from BreastBiomechLib.mesh.primitives import box_mesh
from BreastBiomechLib.solver import ElementMaterials, Loading, Material, Model, Plate
from BreastBiomechLib.solver.placement import compression_plates


@pytest.fixture(scope="module")
def block():
    return box_mesh((40.0, 20.0, 30.0), (4, 2, 3), origin_mm=(-5.0, 2.0, 1.0))


@pytest.mark.parametrize("axis, index", [("LR", 0), ("AP", 1), ("si", 2)])
def test_plates_touch_the_extremes_and_close_by_the_fraction(block, axis, index):
    first, second = compression_plates(block, axis, 0.3)
    lo, hi = block.nodes[:, index].min(), block.nodes[:, index].max()
    assert first.point[index] == pytest.approx(lo) and second.point[index] == pytest.approx(hi)
    assert first.normal[index] == 1.0 and second.normal[index] == -1.0
    gap_after = (second.point + second.displacement - first.point - first.displacement)[index]
    assert gap_after == pytest.approx(0.7 * (hi - lo))
    assert first.displacement @ first.normal == pytest.approx(second.displacement @ second.normal)
    # the default contact nodes are the boundary nodes: here every node but the 2 x 1 interior ones
    assert len(first.slave_nodes) == len(block.nodes) - 3 * 1 * 2


def test_one_moving_plate_and_an_oblique_axis(block):
    fixed, moving = compression_plates(block, "LR", 0.5, moving="second")
    assert np.all(fixed.displacement == 0) and moving.displacement[0] == pytest.approx(-20.0)
    a, b = compression_plates(block, (1.0, 1.0, 0.0), 0.2)
    assert a.normal == pytest.approx(np.array([1.0, 1.0, 0.0]) / np.sqrt(2))
    along = block.nodes @ a.normal
    assert (a.point @ a.normal, b.point @ a.normal) == pytest.approx((along.min(), along.max()))


def test_bad_placements_are_refused(block):
    with pytest.raises(ValueError, match="fraction of the thickness"):
        compression_plates(block, "LR", 25.0)
    with pytest.raises(ValueError, match="unknown compression axis 'XY'"):
        compression_plates(block, "XY", 0.2)
    with pytest.raises(ValueError, match="moving must be one of"):
        compression_plates(block, "LR", 0.2, moving="left")


def test_a_plate_starting_inside_the_tissue_is_refused(block):
    materials = ElementMaterials.uniform(len(block.tets), Material(10e3, 0.45))
    inside = Plate([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [5.0, 0.0, 0.0], np.arange(len(block.nodes)), "paddle")
    with pytest.raises(ValueError, match="'paddle' cuts into the tissue.*up to 5.00 mm"):
        Model(block, materials, Loading(plates=[inside]))
    backwards = Plate([-5.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0], np.arange(len(block.nodes)), "paddle")
    with pytest.raises(ValueError, match="normal points towards the tissue"):
        Model(block, materials, Loading(plates=[backwards]))
