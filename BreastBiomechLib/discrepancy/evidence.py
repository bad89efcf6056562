"""The evidence of a diagnosis round as arrays and images to draw over the measured compressed
image (what the Breast Discrepancy module shows): the landmark residuals, the signed distance of
the model's skin to the measured body, the regions on the measured grid, a candidate's predicted
residual pattern, and the residual magnitude's histogram.

Frames and units: LPS millimetres; images on the measured compressed image's grid; a model's
positions are the fitting mesh's nodes moved by its displacement (N, 3) mm. In a fit of several
measured states, the first state's (a solution in every state is taken at its first part).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk

from BreastBiomechLib.discrepancy.fitted import FittedCase
from BreastBiomechLib.discrepancy.registration import ResidualField
from BreastBiomechLib.landmarks import map_landmarks
from BreastBiomechLib.mesh.tetmesh import boundary_faces

REGION_COLOURS = {"contact": (0.95, 0.6, 0.1), "chest wall": (0.6, 0.2, 0.7), "sub-surface": (0.2, 0.7, 0.9),
                  "tumour": (0.9, 0.1, 0.1), "glandular": (0.95, 0.85, 0.55), "fat": (0.85, 0.75, 0.35),
                  "muscle": (0.7, 0.3, 0.25)}


@dataclass
class LandmarkResiduals:
    """Each landmark's position in the model (``predicted``, (K, 3) LPS mm) and as measured
    (``measured``), their ``labels`` and the distance between them (``error_mm``, K)."""

    labels: list[str]
    predicted: np.ndarray
    measured: np.ndarray
    error_mm: np.ndarray


def landmark_residuals(fitted: FittedCase, displacement_mm: np.ndarray) -> LandmarkResiduals | None:
    """The landmark residuals of the model whose solution is ``displacement_mm``; None when the
    case has no landmarks."""
    if fitted.reference is None:
        return None
    predicted = map_landmarks(fitted.mesh, fitted.first(displacement_mm), fitted.reference).positions
    measured = fitted.measured.positions
    return LandmarkResiduals(list(fitted.reference.labels), predicted, measured,
                             np.linalg.norm(measured - predicted, axis=1))


def skin_surface(fitted: FittedCase, displacement_mm: np.ndarray, surface=None):
    """(points (N, 3) LPS mm, triangles (T, 3), signed distance (N,) mm): the fitting mesh's
    boundary where it is breast skin, moved by ``displacement_mm``, and each point's signed
    distance to the measured body's surface (positive outside it: the model bulges beyond the
    scan; NaN outside the image). ``surface``: a :class:`~BreastBiomechLib.similarity.surface.SurfaceDistance`
    of the measured image (made when not given)."""
    from BreastBiomechLib.similarity.surface import SurfaceDistance

    mesh = fitted.mesh
    faces, _ = boundary_faces(mesh.tets)
    for name in ("breast_skin", "skin"):
        if name in mesh.point_data:
            skin = np.zeros(len(mesh.nodes), bool)
            skin[mesh.node_set(name)] = True
            kept = faces[skin[faces].all(axis=1)]
            if len(kept):
                faces = kept
            break
    used, triangles = np.unique(faces, return_inverse=True)
    points = mesh.nodes[used] + np.asarray(fitted.first(displacement_mm), float)[used]
    surface = surface or SurfaceDistance(fitted.measured_image)
    return points, triangles.reshape(-1, 3), surface.signed_distances(points)


def region_labels(fitted: FittedCase, displacement_mm: np.ndarray,
                  node_regions: np.ndarray) -> tuple[sitk.Image, dict[int, tuple[str, tuple]]]:
    """The regions (:mod:`~BreastBiomechLib.discrepancy.regions`) on the measured grid where the model whose solution is ``displacement_mm`` puts the
    breast: each voxel inside takes the region of the fitting-mesh node nearest to its reference
    position (``node_regions``: one name per node). Returns (label image uint8, {value: (region,
    colour)})."""
    from scipy.spatial import cKDTree

    warper = fitted.problem.warper  # the fit's: its output grid is the measured image's
    displacement_mm = fitted.first(displacement_mm)
    reference = sitk.GetArrayFromImage(warper.nodal_field(displacement_mm, fitted.mesh.nodes))
    inside = sitk.GetArrayFromImage(warper.predict(displacement_mm).inside).astype(bool)
    names = sorted(set(np.asarray(node_regions).tolist()))
    value_of = {name: i + 1 for i, name in enumerate(names)}
    _, nearest = cKDTree(fitted.mesh.nodes).query(reference[inside])
    labels = np.zeros(inside.shape, np.uint8)
    labels[inside] = [value_of[name] for name in np.asarray(node_regions)[nearest]]
    image = sitk.GetImageFromArray(labels)
    image.CopyInformation(fitted.measured_image)
    colours = {value_of[n]: (n, REGION_COLOURS.get(n.split(" ")[0] if n.startswith("contact") else n, (0.5, 0.5, 0.5)))
               for n in names}
    return image, colours


def candidate_pattern(fitted: FittedCase, displacement_mm: np.ndarray, fields: np.ndarray,
                      estimate) -> sitk.Image:
    """What a candidate effect predicts the residual to be: the change of the model's positions
    (mm) its linearised estimate makes (``fields`` (k, N, 3) mm per unit of each parameter, the
    score test's ``estimate`` (k,)), as a magnitude image on the measured grid over the body
    deformed by ``displacement_mm`` (0 outside): comparable with the residual field's magnitude."""
    change = np.tensordot(np.atleast_1d(np.asarray(estimate, float)), np.asarray(fields, float), axes=1)
    field = fitted.problem.warper.nodal_field(fitted.first(displacement_mm), fitted.first(change))
    magnitude = sitk.GetImageFromArray(np.linalg.norm(sitk.GetArrayFromImage(field), axis=-1).astype(np.float32))
    magnitude.CopyInformation(fitted.measured_image)
    return magnitude


def magnitude_histogram(fields: dict[str, ResidualField], bin_mm: float = 0.25) -> dict[str, np.ndarray]:
    """Histograms of the residual magnitude inside each field's mask, on shared bins: {"|r| (mm)":
    bin centres, <name>: the share of the mask's voxels (0-1) in each bin, per field}."""
    if not fields:
        raise ValueError("no residual field to summarise")
    top = max(float(np.percentile(f.magnitude[f.mask], 99.5)) if f.mask.any() else bin_mm for f in fields.values())
    edges = np.arange(0.0, top + bin_mm, bin_mm)
    columns = {"|r| (mm)": (edges[:-1] + edges[1:]) / 2}
    for name, field in fields.items():
        counts, _ = np.histogram(np.minimum(field.magnitude[field.mask], edges[-1] - 1e-9), edges)
        columns[name] = counts / max(int(field.mask.sum()), 1)
    return columns
