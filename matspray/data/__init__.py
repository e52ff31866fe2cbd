"""Data model (cameras, views, scenes), dataset readers and writers, image I/O."""

from matspray.data.camera import Camera, intrinsics_from_fov, pixel_sample_grid
from matspray.data.formats.blender import write_blender
from matspray.data.images import linear_to_srgb, read_image, read_raw, resize, srgb_to_linear, write_image, write_raw
from matspray.data.loader import FORMATS, SceneSummary, describe_scene, detect_format, load_run_scene, load_scene
from matspray.data.scene import Scene, View

__all__ = [
    "Camera",
    "FORMATS",
    "Scene",
    "SceneSummary",
    "View",
    "describe_scene",
    "detect_format",
    "intrinsics_from_fov",
    "linear_to_srgb",
    "load_run_scene",
    "load_scene",
    "pixel_sample_grid",
    "read_image",
    "read_raw",
    "resize",
    "srgb_to_linear",
    "write_blender",
    "write_image",
    "write_raw",
]
