"""`breastbiomech warp` and `breastbiomech compare` on files, end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest
import SimpleITK as sitk

from BreastBiomechLib.cli import main
from BreastBiomechLib.io.markups import read_markups, write_markups
from BreastBiomechLib.io.meshes import write_vtu
from BreastBiomechLib.landmarks import Landmarks
from BreastBiomechLib.mesh.primitives import box_mesh


def test_warp_then_compare(tmp_path, capsys):
    mesh = box_mesh((40.0, 30.0, 20.0), (8, 6, 4), origin_mm=(-20.0, -15.0, -10.0))
    write_vtu(tmp_path / "mesh.vtu", mesh)
    matrix = np.diag([0.8, 1.1, 1.15])
    np.save(tmp_path / "u.npy", mesh.nodes @ (matrix - np.eye(3)).T)
    z, y, x = np.meshgrid(np.arange(24), np.arange(40), np.arange(56), indexing="ij")
    image = sitk.GetImageFromArray((400 + 300 * np.sin(x / 4.0) * np.cos(y / 6.0) + 20 * z).astype(np.float32))
    image.SetOrigin((-27.5, -19.5, -23.0))
    image.SetSpacing((1.0, 1.0, 2.0))
    sitk.WriteImage(image, str(tmp_path / "mr.nrrd"))
    reference = Landmarks([[0.0, 0.0, 0.0], [10.0, 5.0, -4.0]], ["L01", "L02"])
    write_markups(tmp_path / "ref.mrk.json", reference)
    # the "measured" image: SimpleITK's resampling through the inverse of the same affine map
    inverse = sitk.AffineTransform(3)
    inverse.SetMatrix(tuple(np.linalg.inv(matrix).ravel()))
    sitk.WriteImage(sitk.Resample(image, image, inverse, sitk.sitkLinear, 0.0), str(tmp_path / "measured.nrrd"))
    write_markups(tmp_path / "measured.mrk.json", Landmarks(reference.positions @ matrix.T + [0, 0, 1.0],
                                                            reference.labels))

    code = main(["warp", str(tmp_path / "mesh.vtu"), str(tmp_path / "u.npy"), str(tmp_path / "mr.nrrd"),
                 "--like", str(tmp_path / "measured.nrrd"), "--out", str(tmp_path / "predicted.nrrd"),
                 "--inside", str(tmp_path / "inside.nrrd"), "--field", str(tmp_path / "field.mha"),
                 "--landmarks", str(tmp_path / "ref.mrk.json"), "--landmarks-out", str(tmp_path / "pred.mrk.json"),
                 "--device", "cpu"])
    assert code == 0
    assert "voxels inside the deformed mesh" in capsys.readouterr().out
    field = sitk.ReadImage(str(tmp_path / "field.mha"))
    assert field.GetNumberOfComponentsPerPixel() == 3
    np.testing.assert_allclose(read_markups(tmp_path / "pred.mrk.json").positions, reference.positions @ matrix.T,
                               atol=1e-6)

    code = main(["compare", str(tmp_path / "predicted.nrrd"), str(tmp_path / "measured.nrrd"),
                 "--mask", str(tmp_path / "inside.nrrd"), "--device", "cpu", "--json",
                 "--landmarks", str(tmp_path / "ref.mrk.json"), str(tmp_path / "pred.mrk.json"),
                 str(tmp_path / "measured.mrk.json")])
    assert code == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["ncc"] > 0.9999
    assert figures["nmi"] > 1.5
    assert figures["landmarks"]["error_mm"]["mean"] == pytest.approx(1.0, abs=1e-5)  # the measured are 1 mm off

    # a displacement from another mesh is refused with the reason
    np.save(tmp_path / "bad.npy", np.zeros((5, 3)))
    code = main(["warp", str(tmp_path / "mesh.vtu"), str(tmp_path / "bad.npy"), str(tmp_path / "mr.nrrd"),
                 "--out", str(tmp_path / "x.nrrd"), "--device", "cpu"])
    assert code == 2
    assert "from a solve of this mesh" in capsys.readouterr().err
