"""Gaussian Splatting geometry: training with densification and normals, PLY files, evaluation."""

from matspray.geometry.config import GEOMETRY_PRESETS, GeometryConfig, preset
from matspray.geometry.evaluate import evaluate_views, render_view
from matspray.geometry.normals import consensus_normals, depth_normals, oriented_normals, render_normals
from matspray.geometry.ply import read_ply, write_ply
from matspray.geometry.train import train_geometry

__all__ = [
    "GeometryConfig",
    "GEOMETRY_PRESETS",
    "consensus_normals",
    "depth_normals",
    "evaluate_views",
    "oriented_normals",
    "preset",
    "read_ply",
    "render_normals",
    "render_view",
    "train_geometry",
    "write_ply",
]
