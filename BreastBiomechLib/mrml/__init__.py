"""The only bridge between the library and MRML (Slicer's scene). Nothing else imports slicer.

Works inside the Slicer application and headless with the ``slicer-core`` wheel. The library
works in ITK physical space (LPS); MRML nodes hold RAS. Every function here converts, so callers
never flip an axis themselves. Each converter takes the scene explicitly (inside Slicer pass
``slicer.mrmlScene``).
"""

from BreastBiomechLib.mrml.colors import tissue_color_table_node
from BreastBiomechLib.mrml.markups import (
    landmarks_from_markups_node,
    landmarks_to_markups_node,
    plate_from_plane_node,
    plate_to_plane_node,
)
from BreastBiomechLib.mrml.models import tetmesh_from_model_node, tetmesh_to_model_node
from BreastBiomechLib.mrml.parameters import ParameterNode
from BreastBiomechLib.mrml.segmentations import (
    labels_from_segmentation_node,
    labels_to_segmentation_node,
    mask_from_segment,
    mask_to_segment,
    register_segmentation_converters,
)
from BreastBiomechLib.mrml.tables import (
    columns_to_table_node,
    materials_from_table_node,
    materials_to_table_node,
    plot_chart_node,
)
from BreastBiomechLib.mrml.transforms import (
    displacement_field_from_grid_transform_node,
    displacement_field_to_grid_transform_node,
)
from BreastBiomechLib.mrml.volumes import image_from_volume_node, image_to_volume_node

__all__ = [
    "ParameterNode",
    "columns_to_table_node",
    "displacement_field_from_grid_transform_node",
    "displacement_field_to_grid_transform_node",
    "image_from_volume_node",
    "image_to_volume_node",
    "labels_from_segmentation_node",
    "labels_to_segmentation_node",
    "landmarks_from_markups_node",
    "landmarks_to_markups_node",
    "mask_from_segment",
    "mask_to_segment",
    "materials_from_table_node",
    "materials_to_table_node",
    "plate_from_plane_node",
    "plate_to_plane_node",
    "plot_chart_node",
    "register_segmentation_converters",
    "tetmesh_from_model_node",
    "tetmesh_to_model_node",
    "tissue_color_table_node",
]
