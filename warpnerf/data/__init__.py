"""Scenes: the Blender and LLFF loaders, built-in procedural scenes, name resolution, ray spaces.

Importing this package does not import Warp; only generating a built-in scene does.
"""

from warpnerf.data.blender import load_blender
from warpnerf.data.builtin import builtin_scenes, load_builtin
from warpnerf.data.errors import DatasetError
from warpnerf.data.llff import load_llff
from warpnerf.data.rayspace import RaySpace, ndc_rays
from warpnerf.data.resolve import describe_scenes, list_scenes, load_scene
from warpnerf.data.scene import Scene, Views

__all__ = [
    "DatasetError",
    "RaySpace",
    "Scene",
    "Views",
    "builtin_scenes",
    "describe_scenes",
    "list_scenes",
    "load_blender",
    "load_builtin",
    "load_llff",
    "load_scene",
    "ndc_rays",
]
