"""Rasterizing Gaussians into images of any per-Gaussian features: the dispatch to a backend (`rasterize`), the
readable torch reference (`reference`), gsplat on CUDA (`gsplat`) and the frozen views of refinement (`gbuffer`)."""
