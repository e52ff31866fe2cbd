"""The paper's method between the geometry and the asset: lift the 2D maps onto the Gaussians (`lift`), fuse the
per-view estimates (`merger`), refine materials, light and normals with the rendering loss (`refine`), and the
stages around them: the object's masks (`masks`), the cut photos of a capture (`crop`), the ablations' asset
(`asset`), relighting (`relight`), the run's settings (`config`) and the pipeline that runs the stages in order
and resumes them (`pipeline`, with its time estimate in `estimate`)."""
