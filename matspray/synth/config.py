"""Settings of one synthetic benchmark object, checked before anything is rendered or written."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from matspray.errors import SettingError

PLACEMENTS = ("fit", "keep")  # how a glTF asset is placed in the world (matspray.synth.gltf_object)
BACKGROUNDS = ("transparent", "env")  # behind the object in the photos: nothing (alpha = mask) or the light itself
CAMERA_LAYOUTS = ("sphere", "turntable", "front")  # a spiral over an elevation band, one ring, or one side only
TABLETOPS = ("grey", "white-on-dark", "dark-on-light")  # the ground's look, and the object's tone with it

MAX_RESOLUTION = 2048
MAX_VIEWS = 1000
MAX_SPP = 1 << 16


@dataclass
class SynthConfig:
    shape: str = "random"  # a name of matspray.synth.shapes.SHAPES, or 'random' (picked from the seed)
    seed: int = 0
    resolution: int = 128  # pixels, square images
    train_views: int = 40
    test_views: int = 10
    spp: int = 64  # Mitsuba samples per pixel
    env: str = "sky"  # training light: built-in name, .exr/.hdr path, or packaged HDRI name (matspray/hdri)
    relight_envs: list[str] | None = None  # lights for the test views; None: two built-ins unlike `env`
    env_height: int = 128  # lights are resampled to env_height x 2 env_height for rendering
    gt_samples: int = 4  # ground-truth subpixel rays per side (s x s per pixel)
    texture_height: int = 256  # texture rows per part (twice as many columns)
    asset: str | None = None  # a glTF 2.0 file (.glb/.gltf) to render instead of a procedural shape
    placement: str = "fit"  # of the asset: 'fit' (centred, scaled into the unit sphere) or 'keep' (the file's units)
    background: str = "transparent"  # 'env': the photos show the light behind the object and carry no mask
    ground: bool = False  # a grey ground plane under the object in the photos (cameras stay above it)
    cameras: str = "sphere"  # 'turntable': every camera on one ring at one elevation, as a turntable capture
    # 'front': from one side only, a frontal half of the band up to 45 degrees (a hand-held capture of an object on
    # a table against a wall)
    fill: float = 0.92  # the bounding sphere's angular radius as a fraction of half the field of view (> 1: cut)
    tabletop: str = "grey"  # with the ground: 'white-on-dark' a white object on a dark wooden table, 'dark-on-light'
    # a dark object on a light one (both tables textured); 'grey' the plain grey ground and the object's own colours
    overwrite: bool = False  # replace a different scene already in the output folder

    @property
    def unmasked(self) -> bool:
        """Photos without masks: what a real capture gives (true masks stay in the ground truth)."""
        return self.background != "transparent" or self.ground

    def validate(self) -> None:
        """Raise SettingError naming the first setting out of range; normalise env specs to str."""
        for name, value, low, high in (
            ("resolution", self.resolution, 8, MAX_RESOLUTION),
            ("train_views", self.train_views, 1, MAX_VIEWS),
            ("test_views", self.test_views, 0, MAX_VIEWS),
            ("spp", self.spp, 1, MAX_SPP),
            ("seed", self.seed, 0, 2**31 - 1),
            ("env_height", self.env_height, 8, 4096),
            ("gt_samples", self.gt_samples, 1, 16),
            ("texture_height", self.texture_height, 8, 4096),
        ):
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise SettingError(name, f"must be an integer in [{low}, {high}], got {value!r}")
        self.env = str(self.env)
        if self.background not in BACKGROUNDS:
            raise SettingError("background", f"must be one of {', '.join(BACKGROUNDS)}, got {self.background!r}")
        if isinstance(self.fill, bool) or not isinstance(self.fill, (int, float)) or not 0.2 <= self.fill <= 2.0:
            raise SettingError("fill", f"must be a number in [0.2, 2], got {self.fill!r}")
        if self.tabletop not in TABLETOPS:
            raise SettingError("tabletop", f"must be one of {', '.join(TABLETOPS)}, got {self.tabletop!r}")
        if self.tabletop != "grey" and not self.ground:
            raise SettingError("tabletop", f"{self.tabletop!r} is a table: it needs the ground (ground=True)")
        if self.cameras not in CAMERA_LAYOUTS:
            raise SettingError("cameras", f"must be one of {', '.join(CAMERA_LAYOUTS)}, got {self.cameras!r}")
        if self.placement not in PLACEMENTS:
            raise SettingError("placement", f"must be one of {', '.join(PLACEMENTS)}, got {self.placement!r}")
        if self.asset is not None:
            self.asset = str(self.asset)
            if not self.asset.lower().endswith((".glb", ".gltf")):
                raise SettingError("asset", f"{self.asset} is not a .glb or .gltf file")
        if self.relight_envs is not None:
            self.relight_envs = [str(spec) for spec in self.relight_envs]  # as scene.json will hold them
            if len(set(self.relight_envs)) != len(self.relight_envs):
                raise SettingError("relight_envs", f"lists a light twice: {', '.join(self.relight_envs)}")

    def identity(self) -> dict:
        """Everything that determines the files (all settings but `overwrite`)."""
        values = asdict(self)
        values.pop("overwrite")
        defaults = (("background", "transparent"), ("ground", False), ("cameras", "sphere"), ("fill", 0.92))
        for name, default in (*defaults, ("tabletop", "grey")):
            # objects made before these existed keep their identity
            if values[name] == default:
                values.pop(name)
        return values
