"""The named choices of a run in one place: the presets (test, demo, paper), the two methods and the variants, as
plain values and without torch. The stages' configs (`matspray.method.config`, `matspray.geometry.config`), the
demo (`matspray.batch.demo`) and the command line (`matspray.cli.options`, whose `--help` must not import torch) all
read them from here.

Sizes: test is CI-sized (a few seconds a stage), demo a 128 px object or a real capture on a 2-core CPU in minutes,
paper the paper's settings (512 px objects, 30 000 Gaussian Splatting steps) for one GPU.

The variants are the paper's ablations, one registry that refinement, the CLI, the evaluation and the tables read:

  full          Neural Merger with softmax over views, trained with both losses, learns the light
  no-softmax    Neural Merger with unconstrained weights (the paper's softmax ablation)
  supervised    free per-Gaussian materials trained with the 2D-map loss only
  proj-average  the mean of the projected per-view values; no training at all
  no-prior      free per-Gaussian materials from an uninformed grey, trained with the PBR loss alone and a
                learnable light, no 2D maps at all: the R3DGS-like baseline of the paper's Table 1
  photos-only   no-prior for a user's run without 2D maps (its default): a dielectric unless the photos demand
                metal (the metallic starts at `refine.metallic_prior_start` and is pulled down by
                `refine.metallic_prior_weight`); not the paper's baseline, which stays no-prior
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from matspray.errors import ConfigError

# The named lights: the built-in procedural ones (drawn by `matspray.render.shade.lights`) and the packaged HDRIs
# (`matspray/hdri/*.exr`, named by their stem). No name means two lights: `relight --help`, the viewer's menu and the
# error for an unknown name all list `light_names()`.
BUILTIN_LIGHTS = ("sky", "studio", "sunset", "overcast")
HDRI_FOLDER = Path(__file__).resolve().parent / "hdri"  # package data (pyproject's package-data)
HDRI_SUFFIXES = (".exr", ".hdr")


def packaged_hdris() -> dict[str, Path]:
    """Name (file stem) -> path of every .exr / .hdr in the package's HDRI folder, sorted by name."""
    files: dict[str, Path] = {}
    for path in sorted(HDRI_FOLDER.iterdir()) if HDRI_FOLDER.is_dir() else []:
        if path.suffix.lower() in HDRI_SUFFIXES and path.stem not in files:
            files[path.stem] = path
    return files


def light_names() -> str:
    """The named lights as one phrase for help texts and errors."""
    hdris = packaged_hdris()
    return f"built-ins: {', '.join(BUILTIN_LIGHTS)}" + (f"; HDRIs: {', '.join(sorted(hdris))}" if hdris else "")


PRESETS = ("test", "demo", "quality", "paper")
METHODS = ("matspray", "paper")  # matspray: the paper plus the additions below; paper: exactly the paper's method

# the longest image side each preset works at: larger photos are shrunk to it on load unless --downscale is given
# (test: CI-sized; demo: a real capture on a 2-core CPU, quality: the same photos trained on at their full working
# size; paper: 512 px data, and real captures up to 800 px)
WORKING_SIZE = {"test": 128, "demo": 256, "quality": 256, "paper": 800}

# Each preset as a partial config: its changes to the stages' defaults, section by section (the dataclasses' defaults
# are the demo preset, so demo changes nothing). `matspray.method.config.preset_settings` checks every name and type
# against the fields; `iterations` of the geometry stretches its schedule where a preset leaves the rest (`preset`).
PRESET_SETTINGS: dict[str, dict[str, dict]] = {
    "test": {
        "geometry": {
            "resolution": 40,
            "iterations": 60,
            "init_points": 1000,
            "sh_degree": 1,
            "sh_degree_every": 30,
            "densify_from": 20,
            "densify_until": 50,
            "densify_every": 10,
            "max_gaussians": 3000,
            "checkpoint_every": 20,
            "normal_from": 0.5,
        },
        "lift": {"samples_per_side": 2},
        "refine": {"iterations": 30, "envmap_height": 8, "light_warmup": 10},
    },
    "demo": {},
    # demo's sizes, but Gaussian Splatting (and so the lift and refinement of a run without maps) trains on the
    # photos at the working size rather than half of it; 512 px trained worse on held-out photos, and slower
    # (docs/dev/real-captures.md, "The quality preset"); room for three times demo's Gaussians, which the object
    # grows into when densified at a quarter of the threshold, and a longer refinement, which the larger photos'
    # detail needs (docs/dev/camera-light.md, "The skull's LPIPS at quality", and "More Gaussians at quality")
    "quality": {
        "geometry": {"resolution": 256, "max_gaussians": 120_000, "focus_grad_scale": 0.25},
        "refine": {"iterations": 1500},
    },
    "paper": {
        "geometry": {
            "resolution": 512,
            "iterations": 30000,
            "init_points": 100000,
            "sh_degree_every": 1000,
            "densify_from": 500,
            "densify_until": 15000,
            "opacity_reset_every": 3000,
            "max_screen_fraction": 20 / 512,
            "max_gaussians": 1_000_000,
            "checkpoint_every": 2000,
            "normal_from": 0.25,
            "focus_from": 0.1,
        },
        "lift": {"samples_per_side": 16},
        "refine": {"iterations": 10000, "envmap_height": 32, "light_warmup": 1000},
    },
}
# Gaussian Splatting's part of each preset (`matspray.geometry.config.preset`)
GEOMETRY = {name: partial.get("geometry", {}) for name, partial in PRESET_SETTINGS.items()}

# baked shadows (off by default): each preset's changes to `VisibilityConfig`'s shadow maps where they are on
SHADOW_MAPS = {
    "test": {"rows": 4, "resolution": 48},
    "demo": {},
    "quality": {},
    "paper": {"rows": 16, "resolution": 512},
}


@dataclass(frozen=True)
class DemoSize:
    """The benchmark object `matspray demo` makes for a preset."""

    res: int
    views: int
    test_views: int
    spp: int


DEMO_SIZES = {
    "test": DemoSize(res=40, views=8, test_views=2, spp=8),
    "demo": DemoSize(res=128, views=40, test_views=10, spp=64),
    "quality": DemoSize(res=256, views=40, test_views=10, spp=64),
    "paper": DemoSize(res=512, views=100, test_views=200, spp=256),
}


# The sources below name lines of the paper's text (`l.N`), or this where the text is silent: the values the project
# read from the released code
RELEASED = "the paper's released code"


@dataclass(frozen=True)
class Addition:
    """One thing the default method does beyond the paper: the setting, the paper's value of it, and where that
    value comes from (a line of the paper, or the released code where the text is silent)."""

    name: str
    setting: str
    paper: object
    what: str
    source: str


# Every setting where `--method matspray` differs from `--method paper`: `method_settings` sets each to its paper value
# under `paper`, and tests/test_methods_table.py resolves both methods and fails on a difference without a row here.
ADDITIONS = (
    Addition(
        "hull-init",
        "geometry.init",
        "random",
        "objects with masks start Gaussian Splatting from points on the masks' visual hull",
        "l.209: synthetic scenes start from 100 000 points drawn uniformly in a unit cube",
    ),
    Addition(
        "geometry-normals",
        "geometry.predicted_normal_weight",
        0.0,
        "Gaussian Splatting trains on the 2D model's normal maps of every object that has them",
        "l.213: only for highly specular objects (then also l.451: positions fixed)",
    ),
    Addition(
        "min-support",
        "lift.min_support",
        0.0,
        "a view counts for a Gaussian only with >= 0.5 of its best view's hits",
        "eq. 1-3: every view whose rays hit the Gaussian",
    ),
    Addition(
        "unseen-mask",
        "refine.merger.unseen",
        "mean",
        "unseen views get weight 0 (the paper's code fills them with the mean)",
        f"{RELEASED}: views that never saw a Gaussian are filled with the mean of those that did",
    ),
    Addition(
        "pe-octaves",
        "refine.merger.frequencies",
        4,
        "the merger encodes a Gaussian's position with 6 positional-encoding octaves",
        f"l.460 names a NeRF-style encoding without its size; {RELEASED}: 4 octaves",
    ),
    Addition(
        "ablation-offset",
        "refine.merger.unconstrained",
        "raw",
        "the softmax ablation's merger starts at the projection average (weights 1/n_seen plus its output, whose last "
        "layer starts at zero)",
        "l.407, l.417 (the supplement's ablation): the Softmax layer removed, the merger is unconstrained: the MLP's "
        f"outputs, initialised as {RELEASED} initialises its layers, are the weights",
    ),
    Addition(
        "merger-bfloat16",
        "refine.merger.precision",
        "float32",
        "the merger multiplies in bfloat16 on CUDA (and on a CPU with native bfloat16)",
        "l.451: PyTorch on an RTX 4090; no reduced precision is named",
    ),
    Addition(
        "light-warmup",
        "refine.light_warmup",
        0,
        "the light is fitted alone before the merger trains",
        "l.163: one loss supervises the merger and the light together from the start",
    ),
    Addition(
        "light-tv",
        "refine.light_tv_weight",
        0.0,
        "the estimated light is kept smooth by the total variation of its log radiance",
        "l.85: an optimisable environment map, with no prior named",
    ),
    Addition(
        "camera-light",
        "refine.camera_light",
        "off",
        "photos taken with a flash (their EXIF says) are lit by a learned flash at the camera beside the environment",
        "l.85: an optimisable environment map is the only light",
    ),
    Addition(
        "min-coverage",
        "refine.min_coverage",
        0.0,
        "the merger skips Gaussians covering a sliver of a view",
        "l.454: random view sampling, every Gaussian of a view",
    ),
    Addition(
        "normal-neighbours",
        "refine.normal_neighbours",
        0,
        "each Gaussian's normal is averaged over its 16 nearest Gaussians' before shading and refinement",
        "l.84-85: the normals of R3DGS, refined by the rendering loss",
    ),
    Addition(
        "normal-prior",
        "refine.normal_prior_weight",
        0.0,
        "refined normals are held near the geometry's",
        "l.85: normals refined by the rendering loss alone",
    ),
    Addition(
        "refine-normals",
        "refine.predicted_normal_weight",
        0.0,
        "refinement holds the rendered normals near the 2D model's normal maps, where it has them",
        "l.85: normals refined by the rendering loss alone",
    ),
    Addition(
        "metallic-quantile",
        "refine.metallic_quantile",
        0.5,
        "the 2D maps' loss on metallic is least at the lower quartile of the views' (the paper's L1: their median)",
        "l.454: an L1 material loss, whose minimum is the views' median",
    ),
)
# Settings where the text is silent and both methods take the released code's value (docs/method.md shows them)
RELEASED_VALUES = (
    ("lift.footprint_sigmas", 1.0, f"{RELEASED}: a ray hits a Gaussian inside its 1-sigma ellipsoid"),
    ("refine.photo_weight", 2.0, f"{RELEASED}: the photometric term is added twice (l.454 weighs the maps' L1 at 1)"),
)
ADDITION_NAMES = tuple(a.name for a in ADDITIONS)


@dataclass(frozen=True)
class Variant:
    name: str
    label: str  # as the paper's tables write it
    source: str  # what produces the materials: "merger", "free" (per-Gaussian parameters) or "average"
    softmax: bool = True  # merger only: softmax over views (False: the paper's ablation)
    learns_light: bool = False  # trained with the PBR photometric loss and a learnable environment map
    uses_maps: bool = True  # reads the 2D material maps (lifted values, the 2D-map loss); False: needs no predictor
    # a free source's metallic starts at refine.metallic_prior_start and is pulled down by refine.metallic_prior_weight
    # (a dielectric unless the photos demand metal); only this variant reads those two settings
    dielectric_prior: bool = False

    @property
    def trains(self) -> bool:
        return self.source != "average"


VARIANTS: dict[str, Variant] = {
    v.name: v
    for v in (
        Variant("full", "Full", "merger", softmax=True, learns_light=True),
        Variant("proj-average", "Proj. Average", "average"),
        Variant("supervised", "Supervised", "free"),
        Variant("no-softmax", "Without Softmax", "merger", softmax=False, learns_light=True),
        Variant("no-prior", "No prior (R3DGS-like)", "free", learns_light=True, uses_maps=False),
        Variant("photos-only", "Photos only", "free", learns_light=True, uses_maps=False, dielectric_prior=True),
    )
}
VARIANT_NAMES = tuple(VARIANTS)
# refinement's settings that only some variants read: {dotted setting: (whether a variant reads it, what every other
# variant records in its place)}, so that changing one leaves the others' stages and fingerprints alone; None records
# the setting's own default
VARIANT_OWNED_SETTINGS: dict[str, tuple[Callable[[Variant], bool], object]] = {
    "metallic_prior_weight": (lambda v: v.dielectric_prior, 0.0),
    "metallic_prior_start": (lambda v: v.dielectric_prior, 0.5),
    "basecolor_start": (lambda v: v.dielectric_prior, "grey"),
    "merger.unconstrained": (lambda v: v.source == "merger" and not v.softmax, None),
}
# the paper's method, its ablations and its baseline: what `matspray demo` refines and scores (not the user's asset)
PAPER_VARIANTS = tuple(v.name for v in VARIANTS.values() if not v.dielectric_prior)
LABELS = {v.name: v.label for v in VARIANTS.values()}
ABLATION = ("full", "supervised", "proj-average")  # the paper's Table 2
SOFTMAX_ABLATION = ("full", "no-softmax")  # the paper's softmax ablation
BASELINE = "no-prior"  # the paper's Table 1 baseline: materials optimised per scene without a 2D prior
# the paper's relighting PSNR (dB) of Full and what it is compared with: Table 2 (a subset of its objects), the softmax
# ablation (all 17 objects) and Table 1 (all 17; its baseline, the extended R3DGS, is what `no-prior` stands for)
PAPER_ABLATION = {"full": 29.164, "supervised": 24.809, "proj-average": 25.555}
PAPER_SOFTMAX = {"full": 27.282, "no-softmax": 24.600}
PAPER_BASELINE = {"full": 27.282, "no-prior": 25.483}
MAPLESS = tuple(v.name for v in VARIANTS.values() if not v.uses_maps)  # what a run without 2D maps can make
MAPLESS_DEFAULT = "photos-only"  # what it makes unless told: the user's asset (no-prior is the paper's baseline)
# the asset a command takes from a run when none is named, the first of these the run has (else the first it has)
DEFAULT_ASSETS = ("full", MAPLESS_DEFAULT)


def get_variant(name: str) -> Variant:
    if name not in VARIANTS:
        raise ConfigError(f"unknown variant '{name}'; choose one of {', '.join(VARIANT_NAMES)}")
    return VARIANTS[name]


def variants_for_maps(requested: tuple[str, ...] | list[str] | None, has_maps: bool) -> tuple[str, ...]:
    """The variants a run refines: `requested`, or by default `full` (with 2D maps) or `MAPLESS_DEFAULT` (without).
    Without maps, a requested variant that reads them is refused in one line."""
    if requested is None:
        return ("full",) if has_maps else (MAPLESS_DEFAULT,)
    for name in requested:
        if not has_maps and get_variant(name).uses_maps:
            raise ConfigError(
                f"variant '{name}' needs 2D material maps, and this run has none (--predictor none); "
                f"give a predictor (files:DIR, marigold, ...) or ask for {' / '.join(MAPLESS)}"
            )
    return tuple(requested)


def asset_stage(name: str) -> str:
    """Run-folder stage of a variant's asset: `asset/` for the full method, `asset-{variant}/` for ablations."""
    get_variant(name)
    return "asset" if name == "full" else f"asset-{name}"
