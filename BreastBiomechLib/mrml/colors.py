"""The tissue label table as an MRML colour table, for colouring meshes (cell array ``tissue``)
and label-map volumes by tissue."""

from __future__ import annotations

from BreastBiomechLib import labels as lt

TISSUE_COLORS_NAME = "BreastBiomech tissues"


def tissue_color_table_node(scene):
    """The scene's colour table of the label table (one per scene, made on first use): entry
    ``label`` has the tissue's name and colour, entry 0 is transparent background."""
    existing = scene.GetFirstNodeByName(TISSUE_COLORS_NAME)
    if existing is not None and existing.IsA("vtkMRMLColorTableNode"):
        return existing
    node = scene.AddNewNodeByClass("vtkMRMLColorTableNode", TISSUE_COLORS_NAME)
    node.SetTypeToUser()
    node.SetNumberOfColors(max(t.label for t in lt.TISSUES) + 1)
    node.SetColor(lt.BACKGROUND, "background", 0.0, 0.0, 0.0, 0.0)
    for tissue in lt.TISSUES:
        node.SetColor(tissue.label, tissue.name, *tissue.color, 1.0)
    node.SetAttribute("Category", "BreastBiomech")
    return node
