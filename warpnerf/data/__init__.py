"""Scenes: the Blender, LLFF, COLMAP and transforms.json loaders, built-in procedural scenes, name
resolution, and ``warpnerf process`` (photos -> COLMAP -> dataset). A scene's ray space is
:mod:`warpnerf.geometry.rayspace`.

Importing this package does not import Warp; only generating a built-in scene does.
"""

from warpnerf.data.blender import load_blender
from warpnerf.data.builtin import builtin_scenes, load_builtin
from warpnerf.data.errors import DatasetError
from warpnerf.data.llff import load_llff
from warpnerf.data.resolve import describe_scenes, list_scenes, load_scene
from warpnerf.data.scene import Scene, Views

__all__ = [
    "DatasetError",
    "Scene",
    "Views",
    "builtin_scenes",
    "describe_scenes",
    "list_scenes",
    "load_blender",
    "load_builtin",
    "load_llff",
    "load_scene",
]
