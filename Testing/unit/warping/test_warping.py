"""The FE-predicted image and the dense displacement field, against maps whose answer is known:
the identity, and affine displacements checked against SimpleITK's own resampling."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from BreastBiomechLib.mesh.primitives import box_mesh
from BreastBiomechLib.warping import ImageWarper, displacement_field, predict_image
from images import make_image, oblique_direction


@pytest.fixture(scope="module")
def mesh():
    """A 60 x 50 x 40 mm box of tets around the image centre (LPS mm)."""
    return box_mesh((60.0, 50.0, 40.0), (12, 10, 8), origin_mm=(-30.0, -25.0, -20.0))


@pytest.fixture(scope="module")
def image():
    """A smooth image with texture at every scale it is sampled at, 1 x 1.2 x 2 mm voxels, oblique."""
    z, y, x = np.meshgrid(np.arange(36), np.arange(70), np.arange(80), indexing="ij")
    values = 500 + 200 * np.sin(x / 5.0) * np.cos(y / 7.0) + 100 * np.sin(z / 3.0) + 2.0 * x
    direction = oblique_direction() @ np.diag([1.0, 1.0, 1.0])
    centre = -(direction @ (np.array([79, 69, 35]) * [1.0, 1.2, 2.0])) / 2
    return make_image(values.astype(np.float32), (tuple(centre), (1.0, 1.2, 2.0), tuple(direction.ravel())))


def _affine(mesh, matrix, shift):
    """Nodal displacements of the affine map x -> matrix x + shift."""
    return mesh.nodes @ (np.asarray(matrix) - np.eye(3)).T + np.asarray(shift)


def test_the_identity_reproduces_the_input(mesh, image):
    predicted = predict_image(mesh, np.zeros_like(mesh.nodes), image, image, device="cpu")
    inside = sitk.GetArrayFromImage(predicted.inside).astype(bool)
    assert inside.sum() > 0.8 * 60 * 50 * 40 / (1.0 * 1.2 * 2.0)  # the box's voxels are found
    np.testing.assert_allclose(sitk.GetArrayFromImage(predicted.image)[inside],
                               sitk.GetArrayFromImage(image)[inside], rtol=1e-5)
    assert np.all(sitk.GetArrayFromImage(predicted.image)[~inside] == 0)


def test_an_affine_displacement_matches_simpleitk_resampling(mesh, image):
    matrix = np.array([[1.08, 0.05, 0.0], [-0.03, 0.85, 0.04], [0.02, 0.0, 1.12]])  # compression and shear
    shift = np.array([2.5, -1.5, 3.0])
    predicted = predict_image(mesh, _affine(mesh, matrix, shift), image, image, device="cpu", background=-1.0)
    # SimpleITK maps output points to input points: the inverse of the deformation
    inverse = sitk.AffineTransform(3)
    inverse.SetMatrix(tuple(np.linalg.inv(matrix).ravel()))
    inverse.SetTranslation(tuple(-np.linalg.inv(matrix) @ shift))
    reference = sitk.Resample(image, image, inverse, sitk.sitkLinear, -1.0)
    inside = sitk.GetArrayFromImage(predicted.inside).astype(bool)
    assert inside.sum() > 10000
    expected = sitk.GetArrayFromImage(reference)[inside]
    got = sitk.GetArrayFromImage(predicted.image)[inside]
    np.testing.assert_allclose(got, expected, rtol=2e-4, atol=0.05)


def test_the_displacement_field_resamples_like_the_prediction(mesh, image):
    matrix = np.array([[0.9, 0.0, 0.06], [0.0, 1.1, 0.0], [-0.05, 0.0, 1.0]])
    displacement = _affine(mesh, matrix, (1.0, 0.0, -2.0))
    warper = ImageWarper(mesh, image, image, device="cpu")
    predicted = warper.predict(displacement)
    field = displacement_field(mesh, displacement, image, device="cpu")
    assert field.GetNumberOfComponentsPerPixel() == 3 and field.GetSize() == image.GetSize()
    transform = sitk.DisplacementFieldTransform(sitk.Cast(field, sitk.sitkVectorFloat64))
    resampled = sitk.Resample(image, image, transform, sitk.sitkLinear, 0.0)
    inside = sitk.GetArrayFromImage(predicted.inside).astype(bool)
    # the field is the exact inverse map at voxel centres, where ITK evaluates it
    np.testing.assert_allclose(sitk.GetArrayFromImage(resampled)[inside],
                               sitk.GetArrayFromImage(predicted.image)[inside], rtol=2e-4, atol=0.05)
    # and the warper gives the same answer when called again (buffers reused)
    again = warper.predict(displacement)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(again.image), sitk.GetArrayFromImage(predicted.image))


def test_a_linear_nodal_field_is_interpolated_exactly_in_the_deformed_body(mesh, image):
    """Linear shape functions reproduce a field linear in the reference position: at each voxel
    centre inside the deformed body the nodal field equals that function of the voxel's
    reference position (the displacement field gives it); 0 outside."""
    matrix = np.array([[1.05, 0.0, 0.02], [0.01, 0.9, 0.0], [0.0, 0.03, 1.0]])
    displacement = _affine(mesh, matrix, (0.5, -1.0, 1.5))
    gradient, offset = np.array([[0.1, -0.2, 0.05], [0.0, 0.3, 0.1], [-0.04, 0.0, 0.2]]), np.array([1.0, -2.0, 0.5])
    warper = ImageWarper(mesh, image, image, device="cpu")
    field = sitk.GetArrayFromImage(warper.nodal_field(displacement, mesh.nodes @ gradient.T + offset))
    inside = sitk.GetArrayFromImage(warper.predict(displacement).inside).astype(bool)
    k, j, i = np.nonzero(inside)
    centres = np.array([image.TransformIndexToPhysicalPoint((int(a), int(b), int(c))) for a, b, c in zip(i, j, k)])
    reference = centres + sitk.GetArrayFromImage(displacement_field(mesh, displacement, image, device="cpu"))[inside]
    np.testing.assert_allclose(field[inside], reference @ gradient.T + offset, atol=2e-3)
    assert np.all(field[~inside] == 0)
    with pytest.raises(ValueError, match="one 3-vector per node"):
        warper.nodal_field(displacement, np.zeros((3, 3)))


def test_bad_displacements_are_refused(mesh, image):
    warper = ImageWarper(mesh, image, image, device="cpu")
    with pytest.raises(ValueError, match="one 3-vector per node"):
        warper.predict(np.zeros((3, 3)))
    bad = np.zeros_like(mesh.nodes)
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        warper.predict(bad)


@pytest.mark.gpu
def test_cpu_and_cuda_agree(mesh, image):
    import warp as wp

    from BreastBiomechLib.similarity import Similarity

    wp.init()
    if not wp.is_cuda_available():
        pytest.skip("no CUDA device")
    displacement = _affine(mesh, np.diag([0.8, 1.0, 1.25]), (0.0, 1.0, 0.0))
    results = {}
    for device in ("cpu", "cuda"):
        warper = ImageWarper(mesh, image, image, device=device)
        predicted = warper.predict(displacement)
        measure = Similarity(image, device=device)
        results[device] = (sitk.GetArrayFromImage(predicted.image), sitk.GetArrayFromImage(predicted.inside),
                           measure.nmi(warper.warp(displacement)), measure.ncc(warper.warp(displacement)))
    cpu, gpu = results["cpu"], results["cuda"]
    np.testing.assert_array_equal(gpu[1], cpu[1])
    np.testing.assert_allclose(gpu[0], cpu[0], rtol=1e-5, atol=1e-3)
    assert gpu[2] == pytest.approx(cpu[2], abs=1e-6)
    assert gpu[3] == pytest.approx(cpu[3], abs=1e-6)
