"""The FE-predicted deformed MR image (seed section 2.4, step 3): every voxel centre of the
output grid (the measured compressed image's) is located in the deformed mesh, mapped back to
its reference position through the element's shape functions (barycentric coordinates) and the
undeformed image is interpolated there (trilinear). Outside the deformed body: background.

The same map is the dense displacement field that resamples any image of the undeformed
breast into the deformed one (ITK's convention: output point + displacement = input point).

Geometry in LPS millimetres; images are SimpleITK images (any direction); warp kernels run on
CUDA or on the CPU (``device``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
import warp as wp

from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.solver.memory import check_warp_fits
from BreastBiomechLib.timing import staged
from BreastBiomechLib.warping import kernels


def _grid(image: sitk.Image):
    """(origin, index -> LPS matrix, LPS -> index matrix) of an image, float32 for the kernels."""
    to_lps = np.asarray(image.GetDirection(), float).reshape(3, 3) @ np.diag(image.GetSpacing())
    return (wp.vec3(*np.asarray(image.GetOrigin(), np.float32)), wp.mat33(*to_lps.astype(np.float32).ravel()),
            wp.mat33(*np.linalg.inv(to_lps).astype(np.float32).ravel()))


@dataclass
class PredictedImage:
    """``image``: the predicted deformed volume on the output grid (float32); ``inside``: uint8,
    1 where the voxel centre lies in the deformed mesh (the mask to compare images on)."""

    image: sitk.Image
    inside: sitk.Image


class ImageWarper:
    """Warps one undeformed image through displacements of one mesh onto one output grid; the
    mesh, the image and the buffers stay on the device between calls (the optimisation loop's
    use: one :meth:`warp` per forward solve).

    ``mesh``: the reference mesh (LPS mm); ``undeformed``: the image the mesh was built from (or
    any image of the undeformed breast); ``like``: the output grid (the measured deformed image);
    ``background``: the value outside the deformed body. Grids too large for the memory the
    device has free (or ``memory_limit_bytes``) are refused before anything is allocated
    (:class:`~BreastBiomechLib.solver.memory.TooLargeForMemory`)."""

    def __init__(self, mesh: TetMesh, undeformed: sitk.Image, like: sitk.Image, device=None,
                 background: float = 0.0, memory_limit_bytes: int | None = None):
        for name, image in (("undeformed", undeformed), ("output grid", like)):
            if image.GetDimension() != 3:
                raise ValueError(f"the {name} image must be 3D, not {image.GetDimension()}D")
        if undeformed.GetNumberOfComponentsPerPixel() != 1:
            raise ValueError("the undeformed image must be scalar (one value per voxel)")
        wp.init()
        self.device = wp.get_device(device) if device is not None else wp.get_device()
        self.mesh = mesh
        self.like = like
        self.background = float(background)
        self.size = like.GetSize()
        self.voxels = int(np.prod(self.size))
        self._out_grid = _grid(like)
        self._in_grid = _grid(undeformed)
        check_warp_fits(self.voxels, int(np.prod(undeformed.GetSize())), len(mesh.nodes), len(mesh.tets), self.device,
                        memory_limit_bytes)
        with wp.ScopedDevice(self.device):
            self._reference = wp.array(mesh.nodes.astype(np.float32), dtype=wp.vec3)
            self._tets = wp.array(mesh.tets.astype(np.int32), dtype=int)
            self._image = wp.array(sitk.GetArrayFromImage(undeformed).astype(np.float32), dtype=float)
            self._deformed = wp.zeros(len(mesh.nodes), dtype=wp.vec3)
            self._position = wp.zeros(self.voxels, dtype=wp.vec3)
            self._inside = wp.zeros(self.voxels, dtype=wp.int32)
            self._values = wp.zeros(self.voxels, dtype=float)

    def locate(self, displacement_mm: np.ndarray) -> None:
        """Find every output voxel's reference position for nodal displacements (N, 3) mm."""
        displacement = np.asarray(displacement_mm, dtype=np.float64)
        if displacement.shape != self.mesh.nodes.shape:
            raise ValueError(f"displacements must be one 3-vector per node, shape {self.mesh.nodes.shape}; "
                             f"got {displacement.shape}")
        if not np.all(np.isfinite(displacement)):
            raise ValueError("the displacements hold NaN or infinity (a diverged solve?)")
        origin, to_lps, to_index = self._out_grid
        nx, ny, nz = self.size
        with wp.ScopedDevice(self.device):
            self._deformed.assign((self.mesh.nodes + displacement).astype(np.float32))
            self._inside.zero_()
            wp.launch(kernels.locate_in_tets, len(self.mesh.tets),
                      [self._deformed, self._reference, self._tets, origin, to_lps, to_index, nx, ny, nz,
                       self._position, self._inside])

    @staged("image warping")
    def warp(self, displacement_mm: np.ndarray) -> wp.array:
        """The predicted image as a flat device array (z, y, x order) for nodal displacements (N, 3)
        mm; stays on the device (for similarity measures computed there)."""
        self.locate(displacement_mm)
        origin, _, to_index = self._in_grid
        with wp.ScopedDevice(self.device):
            wp.launch(kernels.sample_linear, self.voxels,
                      [self._position, self._inside, self._image, origin, to_index, self.background, self._values])
        return self._values

    @staged("image warping")
    def predict(self, displacement_mm: np.ndarray) -> PredictedImage:
        """The predicted image and the inside mask as SimpleITK images on the output grid."""
        values = self.warp(displacement_mm).numpy().reshape(self.size[::-1])
        inside = self._inside.numpy().reshape(self.size[::-1]).astype(np.uint8)
        return PredictedImage(self._image_like(values), self._image_like(inside))

    def displacement_field(self, displacement_mm: np.ndarray) -> sitk.Image:
        """The dense displacement field on the output grid (vector float64 image, LPS mm): the
        reference position of each voxel centre minus the voxel centre, 0 outside the deformed
        body. ``sitk.DisplacementFieldTransform`` of it resamples any undeformed image into the
        deformed configuration (and ``mrml`` makes it a Slicer grid transform)."""
        self.locate(displacement_mm)
        inside = self._inside.numpy().astype(bool)
        positions = self._position.numpy().astype(np.float64)
        k, j, i = np.unravel_index(np.arange(self.voxels), self.size[::-1])
        origin, to_lps = np.asarray(self.like.GetOrigin()), np.asarray(self.like.GetDirection()).reshape(3, 3) \
            @ np.diag(self.like.GetSpacing())
        centres = origin + np.stack([i, j, k], axis=1) @ to_lps.T
        field = np.where(inside[:, None], positions - centres, 0.0).reshape(*self.size[::-1], 3)
        image = sitk.GetImageFromArray(field, isVector=True)
        image.CopyInformation(self.like)
        return image

    def nodal_field(self, displacement_mm: np.ndarray, values: np.ndarray) -> sitk.Image:
        """Nodal vectors ``values`` (N, 3) (any quantity, e.g. a change of displacement in mm)
        interpolated through the shape functions at every output voxel centre inside the body
        deformed by ``displacement_mm`` (N, 3) mm; 0 outside. A vector float64 image on the
        output grid."""
        values = np.asarray(values, dtype=np.float64)
        if values.shape != self.mesh.nodes.shape:
            raise ValueError(f"nodal values must be one 3-vector per node, shape {self.mesh.nodes.shape}; "
                             f"got {values.shape}")
        self.locate(displacement_mm)
        origin, to_lps, to_index = self._out_grid
        nx, ny, nz = self.size
        with wp.ScopedDevice(self.device):
            nodal = wp.array(values.astype(np.float32), dtype=wp.vec3)
            out = wp.zeros(self.voxels, dtype=wp.vec3)
            inside = wp.zeros(self.voxels, dtype=wp.int32)
            wp.launch(kernels.locate_in_tets, len(self.mesh.tets),
                      [self._deformed, nodal, self._tets, origin, to_lps, to_index, nx, ny, nz, out, inside])
        field = np.where(inside.numpy().astype(bool)[:, None], out.numpy().astype(np.float64), 0.0)
        image = sitk.GetImageFromArray(field.reshape(*self.size[::-1], 3), isVector=True)
        image.CopyInformation(self.like)
        return image

    def _image_like(self, array: np.ndarray) -> sitk.Image:
        image = sitk.GetImageFromArray(array)
        image.CopyInformation(self.like)
        return image


@staged("image warping")
def predict_image(mesh: TetMesh, displacement_mm: np.ndarray, undeformed: sitk.Image, like: sitk.Image,
                  device=None, background: float = 0.0) -> PredictedImage:
    """The FE-predicted deformed image on ``like``'s grid (see :class:`ImageWarper`)."""
    return ImageWarper(mesh, undeformed, like, device, background).predict(displacement_mm)


@staged("image warping")
def displacement_field(mesh: TetMesh, displacement_mm: np.ndarray, like: sitk.Image, device=None) -> sitk.Image:
    """The dense displacement field of the FE solution on ``like``'s grid (see
    :meth:`ImageWarper.displacement_field`)."""
    blank = sitk.Image([2, 2, 2], sitk.sitkFloat32)
    return ImageWarper(mesh, blank, like, device).displacement_field(displacement_mm)
