"""The dataset layouts MatSpray reads (and the synthetic objects write): Blender / NeRF-synthetic transforms, COLMAP,
nerfstudio, TensoIR, and a video with its poses. `matspray.data.loader` chooses the reader by what the folder
holds."""
