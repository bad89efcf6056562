"""Optimisation beyond the material parameters: the fibre direction's angles (seed eq. (6)), the
plates' offsets, and the surface-distance objective.

The fits run on the small synthetic breast of optimisation.synthetic, whose "measured" image is
the prediction at known values, so the truth lies in the fitted family.
"""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from BreastBiomechLib.optimisation import FittingProblem, ParameterSpace, optimise
from BreastBiomechLib.optimisation.forward import FAILED_MM
from BreastBiomechLib.optimisation.space import FreeParameter, fibre_angles, fibre_direction
from BreastBiomechLib.optimisation.synthetic import measured_at, synthetic_case
from BreastBiomechLib.similarity.surface import SurfaceDistance
from BreastBiomechLib.solver import DynamicRelaxation

RELAXATION = DynamicRelaxation(load_iterations=400, tolerance_mm=0.002)
OFFSETS = {"plate1.offset": 1.5, "plate2.offset": -1.0}  # mm: one plate 1.5 mm further in, one 1 mm back


@pytest.fixture(scope="module")
def case():
    return synthetic_case((40.0, 35.0, 40.0), element_mm=6.0, voxel_mm=(2.0, 2.0, 2.0))


@pytest.fixture(scope="module")
def offsets_problem(case):
    """Both plates' offsets free (materials fixed: glandular 30 kPa), measured at :data:`OFFSETS`."""
    space = ParameterSpace.for_model("iso-hetero", ["fat", "glandular"], free=("offset",), plates=2,
                                     start={"glandular.E": 30e3})
    measured = measured_at(case, space, OFFSETS, RELAXATION, device="cpu")
    return FittingProblem(space, case.mesh, case.undeformed, measured, case.planes, objective="nmi+surface",
                          relaxation=RELAXATION, device="cpu")


def test_fibre_angles_follow_the_seeds_equation_6_and_reach_every_direction():
    assert np.allclose(fibre_direction(0.0, 123.0), [0.0, 0.0, 1.0])  # gamma from S
    assert np.allclose(fibre_direction(90.0, 0.0), [1.0, 0.0, 0.0])  # alpha from L ...
    assert np.allclose(fibre_direction(90.0, 90.0), [0.0, 1.0, 0.0])  # ... towards P
    g, a = np.radians(60.0), np.radians(30.0)
    assert np.allclose(fibre_direction(60.0, 30.0), [np.sin(g) * np.cos(a), np.sin(g) * np.sin(a), np.cos(g)])
    for direction in np.random.default_rng(0).standard_normal((200, 3)):
        direction /= np.linalg.norm(direction)
        gamma, alpha = fibre_angles(direction)
        assert 0.0 <= gamma <= 90.0 and 0.0 <= alpha < 360.0  # the default bounds hold every fibre ...
        assert abs(fibre_direction(gamma, alpha) @ direction) == pytest.approx(1.0)  # ... up to its sign


def test_geometric_parameters_scale_linearly_and_are_refused_where_they_mean_nothing():
    gamma = FreeParameter("fibre", "gamma", 0.0, 90.0)
    assert gamma.from_unit(0.5) == pytest.approx(45.0) and gamma.to_unit(9.0) == pytest.approx(0.1)
    offset = FreeParameter("plate2", "offset", -5.0, 5.0)
    assert offset.from_unit(0.25) == pytest.approx(-2.5)
    space = ParameterSpace.for_model("aniso-hetero", ["fat", "glandular"], free=("E", "fibre", "offset"), plates=2,
                                     fibre=(1.0, 0.0, 0.0))
    assert space.keys == ["glandular.E", "fibre.gamma", "fibre.alpha", "plate1.offset", "plate2.offset"]
    start = space.start()  # material ranges' middles, the given fibre, the plates where they were measured
    assert np.allclose(space.fibre_at(start), [1.0, 0.0, 0.0]) and np.allclose(space.plate_offsets(start), 0.0)
    assert start[0] == 0.5
    z = space.unit({"glandular.E": 2e4, "fibre.gamma": 30.0, "fibre.alpha": 90.0, "plate1.offset": 2.0,
                    "plate2.offset": -3.0})
    materials = space.element_materials(z, np.array([1, 2]))
    assert np.allclose(materials.fibre, fibre_direction(30.0, 90.0))
    assert set(space.materials(z)) == {"fat", "glandular"}  # the geometry is no material
    assert space.geometry(z)["plate_offsets_mm"] == pytest.approx([2.0, -3.0])
    assert ParameterSpace.from_dict(space.to_dict()).keys == space.keys
    with pytest.raises(ValueError, match="no fibres"):
        ParameterSpace.for_model("iso-hetero", ["fat"], free=("E", "fibre"))
    with pytest.raises(ValueError, match="plates >= 1"):
        ParameterSpace.for_model("iso-hetero", ["fat"], free=("offset",))
    with pytest.raises(ValueError, match="gamma"):
        FreeParameter("fibre", "gamma", 0.0, 200.0)
    with pytest.raises(ValueError, match="plate offsets are"):
        FreeParameter("fat", "offset", -1.0, 1.0)


def test_the_true_fibre_direction_maximises_nmi(case):
    """Aniso-homo with a stiff fibre (eta 30 kPa): NMI peaks at the fibre direction the measured
    image was made with, against fibres turned in gamma or in alpha."""
    space = ParameterSpace.for_model("aniso-homo", ["fat", "glandular"], free=("fibre",), start={"breast.eta": 30e3})
    truth = {"fibre.gamma": 60.0, "fibre.alpha": 30.0}
    measured = measured_at(case, space, truth, RELAXATION, device="cpu")
    problem = FittingProblem(space, case.mesh, case.undeformed, measured, case.planes, relaxation=RELAXATION,
                             device="cpu")
    at_truth, from_s, turned, tilted = problem.evaluate([
        space.unit(truth), space.unit({"fibre.gamma": 0.0, "fibre.alpha": 30.0}),
        space.unit({"fibre.gamma": 60.0, "fibre.alpha": 120.0}), space.unit({"fibre.gamma": 45.0, "fibre.alpha": 30.0})])
    assert at_truth.nmi > 1.99
    assert max(from_s.nmi, turned.nmi, tilted.nmi) < at_truth.nmi - 0.3


def test_a_fit_recovers_the_plates_offsets(offsets_problem):
    result = optimise(offsets_problem, "cmaes", budget=24, seed=0, population=6)
    assert result.best.values["plate1.offset"] == pytest.approx(OFFSETS["plate1.offset"], abs=0.3)
    assert result.best.values["plate2.offset"] == pytest.approx(OFFSETS["plate2.offset"], abs=0.3)
    assert result.geometry["plate_offsets_mm"] == pytest.approx(list(result.best.values.values()))
    assert result.summary()["geometry"] == result.geometry


def test_the_surface_objective_prefers_the_measured_shape(offsets_problem):
    space = offsets_problem.space
    at_truth, less_compressed = offsets_problem.evaluate([space.unit(OFFSETS),
                                                          space.unit({"plate1.offset": -5.0, "plate2.offset": -5.0})])
    # the stair-stepped mesh meets the smooth measured body (found in the image) within about
    # 2 mm at the truth; plates 5 mm short leave the breast wider than the measured one
    assert at_truth.surface_mm < 2.0 and less_compressed.surface_mm > at_truth.surface_mm + 0.2
    assert at_truth.objective == pytest.approx(-at_truth.nmi + 0.01 * at_truth.surface_mm)
    # a failed solve scores worse than any: for distances too, not a perfect 0 mm
    assert offsets_problem.failed_objective == pytest.approx(0.01 * FAILED_MM)
    assert offsets_problem.failed_objective > less_compressed.objective > at_truth.objective


def test_surface_distance_is_unbiased_on_anisotropic_voxels():
    """A ball of radius 30 mm on 1 x 1 x 2.5 mm voxels: the distance of points at known radii
    to its surface, inside and outside, within the voxelisation of the ball itself (half a
    slice at the poles) and without a bias towards the voxel centres."""
    spacing = np.array([1.0, 1.0, 2.5])
    size = np.array([81, 81, 33])
    origin = -0.5 * (size - 1) * spacing
    k, j, i = np.meshgrid(*(np.arange(n) for n in size[::-1]), indexing="ij")
    r = np.sqrt((origin[0] + i) ** 2 + (origin[1] + j) ** 2 + (origin[2] + 2.5 * k) ** 2)
    body = sitk.GetImageFromArray((r <= 30.0).astype(np.uint8))
    image = sitk.GetImageFromArray(np.where(r <= 30.0, 1000.0, 0.0).astype(np.float32))
    for im in (body, image):
        im.SetSpacing(tuple(spacing))
        im.SetOrigin(tuple(origin))
    surface = SurfaceDistance(image, body)
    directions = np.random.default_rng(1).standard_normal((300, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    for radius in (24.0, 30.0, 34.0):
        distances = surface.distances(radius * directions)
        assert np.abs(distances - abs(radius - 30.0)).max() < 1.25  # half a slice
        assert abs(np.mean(distances) - abs(radius - 30.0)) < 0.25
    assert np.isnan(surface.distances([[0.0, 0.0, 200.0]])[0])  # outside the image: not seen
    empty = sitk.Image(body.GetSize(), sitk.sitkUInt8)
    empty.CopyInformation(body)
    with pytest.raises(ValueError, match="no surface"):
        SurfaceDistance(image, empty)
