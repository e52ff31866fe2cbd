"""Rendering, by concern: `raster/` (rasterizing Gaussians: dispatch, torch reference, gsplat, frozen views), `rays/`
(lifting's ray contributions), `numba/` (the compiled CPU backend of both) and `shade/` (BRDF, environment maps,
deferred shading, visibility, SH). The modules here are what they all share: the blending settings, the projection,
candidate pairs, compositing and blending of hits, the rasterizer's output, the backend choice and the SH constants."""
