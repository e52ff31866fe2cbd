"""Export a run's relightable asset as a textured glTF 2.0 mesh (`matspray export`).

One module per step: `surface` (TSDF fusion of the asset's rendered depth + marching cubes, cleanup),
`decimate` (quadric simplification to a face budget), `contour` (the rim moved onto the asset's
silhouettes), `atlas` (xatlas UV charts), `bake` (textures from the Gaussians' materials, seam padding),
`frames` (dataset Z-up <-> glTF Y-up), `export` (the whole chain and the files it writes)."""
