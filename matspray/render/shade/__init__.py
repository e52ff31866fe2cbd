"""Shading: the metallic-roughness BRDF and its split-sum table, lat-long environment maps and their prefiltering,
deferred image-based lighting of a G-buffer, directional visibility (shadows), spherical harmonics, and bilinear
lookups with a GPU-friendly backward pass."""
