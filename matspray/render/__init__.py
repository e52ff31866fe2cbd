"""Rendering: Gaussian rasterization (G-buffers), ray contributions, PBR shading, environment maps."""
