"""Lifting's ray tracing (paper eq. 1-2): which Gaussians each camera ray hits, front to back, with their response
(`contributions`, the readable torch tracer), and its response kernel on CUDA (`cuda`, `cuda_kernel`)."""
