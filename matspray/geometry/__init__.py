"""Gaussian Splatting geometry: training, densification, normals, PLY files."""
