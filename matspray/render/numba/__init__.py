"""Backend numba: the rasterizer's projection, blending and their backward passes, SH colour, normals, frozen-view
weights and lifting's ray tracing as compiled loops on the CPU. Its kernels are compiled together (`backend.
ensure_compiled`, `python -m matspray.render.numba.compile`), so this package sits above the rays it traces and below
the dispatch that calls it."""
