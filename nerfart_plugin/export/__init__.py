"""Mesh extraction (marching cubes), mesh comparison and video/image writers."""

from nerfart_plugin.export.compare import compare_meshes, displacement_mesh, vertex_distances
from nerfart_plugin.export.mesh import EmptyLevelSetError, MeshExtractor, export_mesh, remove_small_components
from nerfart_plugin.export.video import write_video
from nerfart_plugin.utils.images import save_image, save_image_grid, side_by_side

__all__ = [
    "EmptyLevelSetError",
    "MeshExtractor",
    "compare_meshes",
    "displacement_mesh",
    "export_mesh",
    "remove_small_components",
    "save_image",
    "save_image_grid",
    "side_by_side",
    "vertex_distances",
    "write_video",
]
