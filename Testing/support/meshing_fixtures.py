"""A small analytic breast label map for the meshing tests: a muscle slab on the chest wall
spanning the field of view (cut by it), a half-ellipsoid breast of fat in front, a glandular
ellipsoid and a tumour sphere inside. LPS mm, 1 x 1 x 2.5 mm voxels."""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk

from BreastBiomechLib import labels as lt

BREAST_RADII = (40.0, 32.0, 36.0)  # x, -y (depth), z
GLAND_CENTRE, GLAND_RADII = np.array([0.0, -11.0, 0.0]), np.array([20.0, 11.0, 17.0])
TUMOUR_CENTRE, TUMOUR_RADIUS = np.array([-14.0, -14.0, 4.0]), 5.0  # inside the glandular tissue
MUSCLE_Y = (0.0, 9.0)


def breast_labels(spacing=(1.0, 1.0, 2.5), direction=None) -> sitk.Image:
    """The label map (uint8) on a grid covering x in [-46, 46], y in [-36, 15], z in [-40, 40]: the
    slab is cut by the field of view on four sides, with background (the thorax) behind it."""
    spacing = np.asarray(spacing, float)
    lo, hi = np.array([-46.0, -36.0, -40.0]), np.array([46.0, 15.0, 40.0])
    size = np.floor((hi - lo) / spacing).astype(int)
    origin = lo + 0.5 * spacing
    x, y, z = (origin[a] + spacing[a] * np.arange(size[a]) for a in range(3))
    X, Y, Z = x[None, None, :], y[None, :, None], z[:, None, None]
    a, d, b = BREAST_RADII
    labels = np.zeros((size[2], size[1], size[0]), np.uint8)
    breast = ((X / a) ** 2 + (Y / d) ** 2 + (Z / b) ** 2 <= 1.0) & (Y < 0)
    labels[np.broadcast_to(breast, labels.shape)] = lt.FAT.label
    gland = (((X - GLAND_CENTRE[0]) / GLAND_RADII[0]) ** 2 + ((Y - GLAND_CENTRE[1]) / GLAND_RADII[1]) ** 2
             + ((Z - GLAND_CENTRE[2]) / GLAND_RADII[2]) ** 2 <= 1.0)
    labels[np.broadcast_to(gland & breast, labels.shape)] = lt.GLANDULAR.label
    tumour = (X - TUMOUR_CENTRE[0]) ** 2 + (Y - TUMOUR_CENTRE[1]) ** 2 + (Z - TUMOUR_CENTRE[2]) ** 2 <= TUMOUR_RADIUS**2
    labels[np.broadcast_to(tumour & breast, labels.shape)] = lt.TUMOUR.label
    muscle = (Y >= MUSCLE_Y[0]) & (Y < MUSCLE_Y[1])
    labels[np.broadcast_to(muscle, labels.shape)] = lt.MUSCLE.label
    image = sitk.GetImageFromArray(labels)
    image.SetSpacing(tuple(spacing))
    image.SetOrigin(tuple(origin))
    if direction is not None:  # rotate the grid about the origin of physical space
        image.SetDirection(tuple(np.asarray(direction, float).ravel()))
        image.SetOrigin(tuple(np.asarray(direction, float).reshape(3, 3) @ origin))
    return image
