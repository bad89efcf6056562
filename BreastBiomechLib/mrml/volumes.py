"""SimpleITK images (LPS) <-> MRML scalar and label-map volume nodes (RAS), geometry exact."""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
import vtk
from vtk.util import numpy_support as nps

from BreastBiomechLib.mrml import frames


def _image_data(array: np.ndarray):
    nz, ny, nx = array.shape[:3]
    components = 1 if array.ndim == 3 else array.shape[3]
    data = vtk.vtkImageData()
    data.SetDimensions(nx, ny, nz)
    scalars = nps.numpy_to_vtk(np.ascontiguousarray(array).reshape(nx * ny * nz, components), deep=True)
    data.GetPointData().SetScalars(scalars)
    return data


def image_to_volume_node(image: sitk.Image, scene, name: str = "Volume", labelmap: bool = False, node=None,
                         display: bool = True):
    """Put a 3D scalar SimpleITK image into a (new or given) volume node; returns the node.

    ``labelmap`` makes a vtkMRMLLabelMapVolumeNode; ``display=False`` skips display nodes (for
    nodes that only carry data between Slicer functions). The node's IJK-to-RAS matrix is the image's
    index-to-LPS geometry flipped to RAS, so physical positions are preserved exactly."""
    if image.GetDimension() != 3 or image.GetNumberOfComponentsPerPixel() != 1:
        raise ValueError("a 3D scalar image is needed for a volume node "
                         f"(got {image.GetDimension()}D with {image.GetNumberOfComponentsPerPixel()} components)")
    if node is None:
        cls = "vtkMRMLLabelMapVolumeNode" if labelmap else "vtkMRMLScalarVolumeNode"
        node = scene.AddNewNodeByClass(cls, name)
        if display:
            node.CreateDefaultDisplayNodes()
    ijk_to_lps = frames.ijk_to_lps(image.GetOrigin(), image.GetSpacing(), image.GetDirection())
    ijk_to_ras = np.diag([-1.0, -1.0, 1.0, 1.0]) @ ijk_to_lps
    node.SetIJKToRASMatrix(frames.to_vtk_matrix(ijk_to_ras))
    node.SetAndObserveImageData(_image_data(sitk.GetArrayFromImage(image)))
    return node


def image_from_volume_node(node) -> sitk.Image:
    """The volume node's voxels and geometry as a SimpleITK image in LPS (transforms applied to
    the node in the scene are not hardened here)."""
    if node is None or node.GetImageData() is None:
        raise ValueError("the volume node has no image data; load or create a volume first")
    ijk_to_ras = vtk.vtkMatrix4x4()
    node.GetIJKToRASMatrix(ijk_to_ras)
    ijk_to_lps = np.diag([-1.0, -1.0, 1.0, 1.0]) @ frames.from_vtk_matrix(ijk_to_ras)
    origin, spacing, direction = frames.geometry_from_ijk_to_lps(ijk_to_lps)
    data = node.GetImageData()
    nx, ny, nz = data.GetDimensions()
    scalars = data.GetPointData().GetScalars()
    array = nps.vtk_to_numpy(scalars).reshape(nz, ny, nx, -1)
    image = sitk.GetImageFromArray(array[..., 0].copy() if array.shape[3] == 1 else array.copy(),
                                   isVector=array.shape[3] > 1)
    image.SetOrigin(tuple(origin))
    image.SetSpacing(tuple(spacing))
    image.SetDirection(tuple(direction.ravel()))
    return image

