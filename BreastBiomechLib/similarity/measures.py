"""Image similarity of the FE-predicted and the measured deformed image (seed section 2.4,
step 4): normalised mutual information, NMI(A, B) = (H(A) + H(B)) / H(A, B) with Shannon
entropies of the (joint) intensity histograms (the seed's eq. (16), Studholme et al. 1999), and
normalised cross-correlation. 2 is NMI's maximum (B a one-to-one relabelling of A), 1 its value
for independent images.

Computed on the device over a mask of voxels; :class:`Similarity` keeps the measured image on
the device for the optimisation loop, where the predicted image arrives as a device array from
:class:`BreastBiomechLib.warping.ImageWarper`.
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
import warp as wp

from BreastBiomechLib.similarity import kernels
from BreastBiomechLib.timing import staged

CHUNK = 64  # voxels per thread in the reductions


def entropies(histogram: np.ndarray) -> tuple[float, float, float]:
    """H(A), H(B), H(A, B) (nats) of a joint histogram (bins of A along axis 0)."""
    total = histogram.sum()
    if total <= 0:
        raise ValueError("the mask holds no voxels: there is nothing to compare")
    p = histogram / total

    def h(q):
        q = q[q > 0]
        return float(-(q * np.log(q)).sum())

    return h(p.sum(axis=1)), h(p.sum(axis=0)), h(p.ravel())


def _flat(image) -> np.ndarray:
    if isinstance(image, sitk.Image):
        return sitk.GetArrayViewFromImage(image).astype(np.float32).ravel()
    return np.asarray(image, dtype=np.float32).ravel()


class Similarity:
    """NMI and NCC of predicted images against one measured image, on ``device``.

    ``measured``: SimpleITK image or array; ``mask``: voxels compared (bool array or image of the
    measured grid; default all); ``bins``: histogram bins per image (64); ``range_measured`` and
    ``range_predicted``: the intensity ranges binned (default: the measured image's minimum and
    maximum over the mask, for both: the predicted image is the undeformed MR, same units)."""

    def __init__(self, measured, mask=None, bins: int = 64, range_measured=None, range_predicted=None,
                 device=None):
        if bins < 2:
            raise ValueError("NMI needs at least 2 histogram bins per image")
        values = _flat(measured)
        keep = np.ones(values.size, bool) if mask is None else _flat(mask).astype(bool)
        if keep.size != values.size:
            raise ValueError(f"the mask has {keep.size} voxels, the measured image {values.size}")
        if not keep.any():
            raise ValueError("the mask selects no voxel: there is nothing to compare")
        if range_measured is None:
            range_measured = (float(values[keep].min()), float(values[keep].max()))
        self.ranges = [self._check_range(range_measured, "measured"),
                       self._check_range(range_predicted or range_measured, "predicted")]
        self.bins = int(bins)
        self.voxels = values.size
        wp.init()
        self.device = wp.get_device(device) if device is not None else wp.get_device()
        self._shift = float(values[keep].mean())
        with wp.ScopedDevice(self.device):
            self._measured = wp.array(values, dtype=float)
            self._mask = wp.array(keep.astype(np.int32), dtype=wp.int32)
            self._histogram = wp.zeros(self.bins * self.bins, dtype=float)
            self._sums = wp.zeros(6, dtype=wp.float64)

    @staticmethod
    def _check_range(value, what):
        low, high = (float(v) for v in value)
        if not high > low:
            raise ValueError(f"the {what} intensity range [{low:g}, {high:g}] is empty: the image is constant "
                             "over the mask, or give the range explicitly")
        return low, high

    def _device_array(self, predicted) -> wp.array:
        if isinstance(predicted, wp.array):
            if predicted.shape[0] != self.voxels:
                raise ValueError(f"the predicted image has {predicted.shape[0]} voxels, the measured {self.voxels}")
            return predicted
        values = _flat(predicted)
        if values.size != self.voxels:
            raise ValueError(f"the predicted image has {values.size} voxels, the measured {self.voxels}")
        with wp.ScopedDevice(self.device):
            return wp.array(values, dtype=float)

    def joint_histogram(self, predicted) -> np.ndarray:
        """(bins, bins) counts: measured bins along axis 0, predicted along axis 1."""
        b = self._device_array(predicted)
        (a_low, a_high), (b_low, b_high) = self.ranges
        with wp.ScopedDevice(self.device):
            self._histogram.zero_()
            wp.launch(kernels.joint_histogram, (self.voxels + CHUNK - 1) // CHUNK,
                      [self._measured, b, self._mask, a_low, self.bins / (a_high - a_low), b_low,
                       self.bins / (b_high - b_low), self.bins, CHUNK, self._histogram])
            return self._histogram.numpy().reshape(self.bins, self.bins).astype(np.float64)

    @staged("similarity")
    def nmi(self, predicted) -> float:
        """(H(A) + H(B)) / H(A, B), A the measured and B the predicted image (1 to 2)."""
        h_a, h_b, h_ab = entropies(self.joint_histogram(predicted))
        return (h_a + h_b) / h_ab if h_ab > 0 else 2.0

    @staged("similarity")
    def ncc(self, predicted) -> float:
        """Pearson correlation of the two images over the mask (-1 to 1); 0 if either is constant."""
        b = self._device_array(predicted)
        with wp.ScopedDevice(self.device):
            self._sums.zero_()
            wp.launch(kernels.pair_moments, (self.voxels + CHUNK - 1) // CHUNK,
                      [self._measured, b, self._mask, self._shift, self._shift, CHUNK, self._sums])
            n, sa, sb, saa, sbb, sab = self._sums.numpy()
        var_a, var_b = saa - sa * sa / n, sbb - sb * sb / n
        if var_a <= 0 or var_b <= 0:
            return 0.0
        return float((sab - sa * sb / n) / np.sqrt(var_a * var_b))


@staged("similarity")
def nmi(measured, predicted, mask=None, bins: int = 64, range_measured=None, range_predicted=None,
        device=None) -> float:
    """NMI of two images of one grid (see :class:`Similarity`); each image's range defaults to
    its own minimum and maximum over the mask."""
    if range_predicted is None:
        values = _flat(predicted)
        keep = slice(None) if mask is None else _flat(mask).astype(bool)
        range_predicted = (float(values[keep].min()), float(values[keep].max()))
    return Similarity(measured, mask, bins, range_measured, range_predicted, device).nmi(predicted)


@staged("similarity")
def ncc(measured, predicted, mask=None, device=None) -> float:
    """Normalised cross-correlation of two images of one grid over the mask."""
    return Similarity(measured, mask, device=device, range_measured=(0.0, 1.0)).ncc(predicted)
