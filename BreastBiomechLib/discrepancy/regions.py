"""Where in the breast a feature sits: the regions residuals are summarised by and effects act in.

Regions, in the undeformed fitting mesh (LPS mm), first match wins:
``tumour`` (within :data:`BAND_MM` of a tumour element), ``contact <plate>`` (within
:data:`BAND_MM` of the skin nodes touching that plate at the fit's solution), ``chest wall``
(within :data:`CHEST_BAND_MM` of the chest-wall nodes), ``sub-surface`` (within :data:`BAND_MM`
of the skin), and deeper ``glandular``, ``muscle`` or ``fat`` by the tissue of the element that
holds the point. In a fit of several measured states, a feature's contact bands are its own
state's (:func:`feature_regions`).
"""

from __future__ import annotations

import numpy as np

from BreastBiomechLib import labels
from BreastBiomechLib.landmarks.mapping import locate_points

BAND_MM = 10.0
CHEST_BAND_MM = 15.0
TOUCH_MM = 0.5  # a contact node within this of its plate's final plane touches it


def _near(points: np.ndarray, targets: np.ndarray, distance: float) -> np.ndarray:
    from scipy.spatial import cKDTree

    if len(targets) == 0:
        return np.zeros(len(points), bool)
    gap, _ = cKDTree(targets).query(points)
    return gap <= distance


def touching(plate, nodes_mm: np.ndarray, displacement_mm: np.ndarray) -> np.ndarray:
    """The contact nodes of ``plate`` within :data:`TOUCH_MM` of its final plane (node ids)."""
    final = nodes_mm[plate.slave_nodes] + displacement_mm[plate.slave_nodes]
    gap = (final - (plate.point + plate.displacement)) @ plate.normal
    return plate.slave_nodes[gap <= TOUCH_MM]


def regions_of(fitted, points: np.ndarray, displacement_mm: np.ndarray) -> np.ndarray:
    """The region name of each point (K, 3) LPS mm of ``fitted``'s undeformed mesh, with the plate
    contact taken from the solution ``displacement_mm`` (N, 3)."""
    mesh = fitted.mesh
    points = np.asarray(points, float).reshape(-1, 3)
    out = np.full(len(points), "", dtype=object)

    def assign(mask, name):
        out[(out == "") & mask] = name

    tumour = fitted.tissue == labels.TUMOUR.label
    if tumour.any():
        assign(_near(points, mesh.nodes[np.unique(mesh.tets[tumour])], BAND_MM), "tumour")
    for plate in fitted.plates:
        assign(_near(points, mesh.nodes[touching(plate, mesh.nodes, displacement_mm)], BAND_MM), f"contact {plate.name}")
    if "chest_wall" in mesh.point_data:
        assign(_near(points, mesh.nodes[mesh.node_set("chest_wall")], CHEST_BAND_MM), "chest wall")
    skin = mesh.node_set("skin" if "skin" in mesh.point_data else "surface")
    assign(_near(points, mesh.nodes[skin], BAND_MM), "sub-surface")
    rest = out == ""
    if rest.any():
        where = locate_points(mesh, points[rest])
        out[rest] = [labels.tissue(int(t)).name for t in fitted.tissue[where.tets]]
    return out.astype(str)


def feature_regions(fitted, observations, displacement_mm: np.ndarray) -> np.ndarray:
    """The region of each feature of ``observations`` (n,) at the solution ``displacement_mm`` (in
    every measured state of ``fitted``, stacked): each feature's contact bands those of its own state."""
    if not fitted.further:
        return regions_of(fitted, observations.points, displacement_mm)
    out = np.empty(len(observations), dtype=object)
    for state, u in zip(fitted.states, fitted.split(displacement_mm)):
        mine = observations.in_state(state.name)
        out[mine] = regions_of(state, observations.points[mine], u)
    return out.astype(str)
