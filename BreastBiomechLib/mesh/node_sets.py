"""Loading node sets of a breast mesh built from a label image: the chest wall (the pectoral
muscle's exposed posterior surface), the cut faces where the label map met the edge of the field
of view, the skin surface (contact candidates), the nipple.

Nodes in LPS mm; posterior is +y, anterior -y (ITK physical space)."""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk

from BreastBiomechLib import labels as lt
from BreastBiomechLib.mesh.tetmesh import TetMesh, boundary_faces
from BreastBiomechLib.surface.extract import index_to_physical

POSTERIOR = np.array([0.0, 1.0, 0.0])


def chest_front_y(mesh: TetMesh, tissue: np.ndarray, chest_wall: np.ndarray) -> float | None:
    """The LPS y (mm) of the most anterior muscle node (without muscle elements, of the most
    anterior ``chest_wall`` node, a boolean (N,) mask): where the breast starts. None when the
    mesh has neither."""
    muscle = np.unique(mesh.tets[np.asarray(tissue) == lt.MUSCLE.label])
    base = muscle if len(muscle) else np.flatnonzero(chest_wall)
    return float(mesh.nodes[base, 1].min()) if len(base) else None


def breast_node_sets(mesh: TetMesh, tissue: np.ndarray, labels: sitk.Image,
                     nipple_mm: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Node sets as uint8 point arrays (1 = in the set):

    - ``fov_cut``: nodes of boundary faces lying on a face of the label map's field of view
      (the body continues there; held fixed in a loading case);
    - ``chest_wall``: nodes of the other boundary faces of muscle elements (``tissue`` (M,)
      label values) that face posteriorly (outward normal within 60 degrees of +y): the pectoral
      surface on the chest wall; without muscle, the boundary faces facing posteriorly (normal
      within 45 degrees of +y);
    - ``skin``: the remaining boundary nodes;
    - ``breast_skin``: the skin nodes anterior to the muscle's most anterior node (without
      muscle, the chest wall's): the breast itself, which compression plates touch (contact
      candidates; plates are placed tangent to it);
    - ``nipple``: the skin node nearest ``nipple_mm`` (3,), or the most anterior skin node.
    """
    faces, owner = boundary_faces(mesh.tets)
    A, origin = index_to_physical(labels)
    ijk = (mesh.nodes - origin) @ np.linalg.inv(A).T
    size = np.array(labels.GetSize())
    # the label map's field of view ends half a voxel beyond the outer voxel centres
    on_cut = np.zeros(len(faces), bool)
    for axis in range(3):
        for plane in (-0.5, size[axis] - 0.5):
            on_cut |= (np.abs(ijk[faces, axis] - plane) < 0.5).all(axis=1)  # within half a voxel
    p = mesh.nodes[faces]
    normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    facing_back = normals @ POSTERIOR
    if (tissue == lt.MUSCLE.label).any():
        chest = ~on_cut & (tissue[owner] == lt.MUSCLE.label) & (facing_back > 0.5)
    else:
        chest = ~on_cut & (facing_back > np.cos(np.radians(45)))
    n = len(mesh.nodes)

    def nodes_of(mask: np.ndarray) -> np.ndarray:
        flags = np.zeros(n, bool)
        flags[faces[mask].ravel()] = True
        return flags

    cut, chest_wall = nodes_of(on_cut), nodes_of(chest)
    chest_wall &= ~cut
    skin = nodes_of(~on_cut & ~chest) & ~cut & ~chest_wall
    if not skin.any():
        raise ValueError("the mesh has no skin surface: every boundary face is chest wall or field-of-view cut")
    skin_ids = np.flatnonzero(skin)
    if nipple_mm is None:
        nipple = skin_ids[np.argmin(mesh.nodes[skin_ids, 1])]  # most anterior (-y)
    else:
        nipple = skin_ids[np.argmin(np.linalg.norm(mesh.nodes[skin_ids] - np.asarray(nipple_mm, float), axis=1))]
    nipple_flag = np.zeros(n, bool)
    nipple_flag[nipple] = True
    breast = skin.copy()
    front = chest_front_y(mesh, tissue, chest_wall)
    if front is not None:
        breast &= mesh.nodes[:, 1] < front
    if not breast.any():
        raise ValueError("no skin lies anterior to the chest wall: is the label map's anterior direction -y (LPS)?")
    return {name: flags.astype(np.uint8) for name, flags in
            (("fov_cut", cut), ("chest_wall", chest_wall), ("skin", skin), ("breast_skin", breast),
             ("nipple", nipple_flag))}
