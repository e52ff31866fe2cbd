"""Settings of `matspray export`, checked once where they are made."""

from __future__ import annotations

from dataclasses import dataclass

from matspray.errors import SettingError

FRAMES = ("gltf", "dataset")
BAKES = ("auto", "views", "gaussians")
MIN_FACES = 100
TEXTURE_SIZES = tuple(2**k for k in range(6, 14))  # 64 .. 8192


@dataclass(frozen=True)
class ExportConfig:
    faces: int = 50_000  # face budget of the decimated mesh (a common budget for one real-time asset)
    texture_size: int = 1024  # side of the square textures (a power of two in [64, 8192])
    frame: str = "gltf"  # gltf: Y-up; dataset: the dataset's world coordinates (Z-up)
    grid: int = 128  # TSDF voxels along the longest side of the object's box (the atlas' time grows fast with the
    # faces this makes)
    truncation: float = 4.0  # TSDF truncation, in voxels
    min_alpha: float = 0.5  # rendered coverage above which a pixel holds surface (below: free space)
    keep_fraction: float = 0.05  # keep connected components with at least this share of the largest one's faces
    neighbours: int = 16  # Gaussians blended per texel when baking in 3D (texels no bake view sees)
    bake: str = "auto"  # where texels read materials: views (the asset's renders at the training views), gaussians
    # (the Gaussians around each texel, blended in 3D), auto (views for the assets made without 2D maps, whose
    # Gaussians' materials are noisy one by one, gaussians for the others; `export_run` resolves it from the variant;
    # docs/defaults.md)
    padding: int = 4  # xatlas gutter between charts, in texels
    asset_normals: float = 0.5  # share of the Gaussians' refined normals in the vertex normals (0: the surface's own);
    # the two sources err in different places, so their mix relights better than either (docs/defaults.md)
    normal_smoothing: int = 10  # Taubin passes on the copy of the surface its normals come from (0: the raw surface's)
    silhouette_rounds: int = 2  # rounds moving the decimated mesh's rim vertices onto the asset's silhouettes (0: off)

    def __post_init__(self):
        if self.faces < MIN_FACES:
            raise SettingError("export.faces", f"the face budget must be >= {MIN_FACES}, got {self.faces}")
        if self.texture_size not in TEXTURE_SIZES:
            raise SettingError(
                "export.texture_size", f"the texture size must be a power of two in [64, 8192], got {self.texture_size}"
            )
        if self.frame not in FRAMES:
            raise SettingError("export.frame", f"unknown frame '{self.frame}'; choose one of {', '.join(FRAMES)}")
        if self.grid < 16 or self.truncation <= 0 or not 0 < self.min_alpha < 1 or not 0 <= self.keep_fraction <= 1:
            raise SettingError(
                "export",
                "the TSDF grid must be >= 16 voxels, the truncation > 0, the alpha threshold in (0, 1) "
                "and the kept component share in [0, 1]",
            )
        if not 0 <= self.asset_normals <= 1:
            raise SettingError(
                "export.asset_normals",
                f"the Gaussians' share of the normals must be in [0, 1], got {self.asset_normals}",
            )
        if self.neighbours < 1 or self.padding < 0:
            raise SettingError("export", "baking needs >= 1 neighbour and a padding >= 0")
        if self.normal_smoothing < 0:
            raise SettingError(
                "export.normal_smoothing", f"the normals' smoothing passes must be >= 0, got {self.normal_smoothing}"
            )
        if self.bake not in BAKES:
            raise SettingError("export.bake", f"unknown bake '{self.bake}'; choose one of {', '.join(BAKES)}")
        if self.silhouette_rounds < 0:
            raise SettingError(
                "export.silhouette_rounds", f"the silhouette fit's rounds must be >= 0, got {self.silhouette_rounds}"
            )
