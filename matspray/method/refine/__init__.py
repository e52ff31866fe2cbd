"""Refinement (paper section 3.4): materials, the environment light and the shading normals optimised by the
PBR rendering loss on frozen geometry. `loop` runs it, `steps` is the optimisation loop's bookkeeping, `terms`
the loss terms, `normals` the refined shading normals and `metallic` the metallic fit of the supervised variant."""
