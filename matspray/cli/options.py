"""The method's command-line options, shared by `run`, `demo`, `bench` and `batch`: each flag sets one named
setting of `matspray.method.config` (the library validates; a bad value comes back as a SettingError, and
`matspray.cli.main` names the flag that set it). Nothing here imports torch, so `--help` stays fast.

The research settings are reached by name, `--set KEY=VALUE` (`matspray.cli.settings`); the flags that set them one
by one (`--min-support`, `--geometry-iterations`, ...) still parse, hidden from the help, for the scripts and
benchmarks that use them (benchmarks add them all through `add_method_arguments`)."""

from __future__ import annotations

import argparse
import os

from matspray.cli.settings import NotFinite, finite_float
from matspray.presets import ADDITION_NAMES, METHODS, PRESETS, VARIANT_NAMES


def on_off(value: str) -> bool:
    if value not in ("on", "off"):
        raise ValueError(value)
    return value == "on"


DEVICE_HELP = "auto (CUDA when available; default), cpu, cuda or cuda:N"
BACKEND_HELP = (
    "rasterizer: auto (default; on CUDA gsplat when its CUDA code builds, else torch; on the CPU numba), "
    "torch (the readable reference), numba (compiled, CPU only) or gsplat (CUDA only; pip install 'matspray[cuda]')"
)

# flag -> (setting, how the flag's text becomes the setting's value, help); None values mean "not given"
SETTING_FLAGS = {
    "--geometry-iterations": (
        "geometry.iterations",
        int,
        "override the preset's Gaussian Splatting iterations (the schedule follows)",
    ),
    "--refine-iterations": ("refine.iterations", int, "override the preset's refinement iterations"),
    "--samples-per-side": (
        "lift.samples_per_side",
        int,
        "override the preset's k (k x k lifting rays per pixel, 1..32)",
    ),
    "--min-support": (
        "lift.min_support",
        finite_float,
        "a view counts for a Gaussian when it gets at least this share of the hits of "
        "its best view (matspray: 0.5; paper: 0, every view with a hit)",
    ),
    "--transmittance-threshold": (
        "lift.visibility_threshold",
        finite_float,
        "lifting writes only into hits whose transmittance in "
        "front is at least this (default 0, every hit, as the paper)",
    ),
    "--footprint": (
        "lift.footprint_sigmas",
        lambda v: {"core": 1.0, "all": None}[v],
        "which hits feed a Gaussian's per-view median: core (rays within 1 sigma; matspray) or all (paper)",
    ),
    "--merger-seen-input": (
        "refine.merger.seen_input",
        on_off,
        "on: the merger also reads which views saw each Gaussian; "
        "off (default, as the paper): position and values only",
    ),
    "--merger-precision": (
        "refine.merger.precision",
        str,
        "the merger's matrix products: auto (default: bfloat16 on a CUDA GPU and on a CPU with native bfloat16, "
        "where refinement runs faster; float32 elsewhere; docs/defaults.md), float32 or bfloat16",
    ),
    "--unseen": (
        "refine.merger.unseen",
        str,
        "views that never hit a Gaussian: mask (weight 0; matspray) or mean (filled with "
        "the mean of the views that did; paper)",
    ),
    "--basecolor-loss": (
        "refine.basecolor_loss",
        str,
        "l1 (default, as the paper), scale-invariant (forgives each view's "
        "exposure error) or huber (averages views "
        "that differ by less "
        "than --basecolor-huber-delta, outvotes those that differ by more)",
    ),
    "--basecolor-huber-delta": (
        "refine.basecolor_huber_delta",
        finite_float,
        "with --basecolor-loss huber: the base-colour residual "
        "(linear) where the loss turns from quadratic to linear (default 0.05)",
    ),
    "--photo-weight": (
        "refine.photo_weight",
        finite_float,
        "weight of the photometric loss against the material loss, in the variants with both "
        "(the paper's released code: 2; the text is silent)",
    ),
    "--light-warmup": (
        "refine.light_warmup",
        int,
        "steps that fit the light alone before the merger trains (paper: 0)",
    ),
    "--min-coverage": (
        "refine.min_coverage",
        finite_float,
        "the merger skips Gaussians covering fewer pixels of a view (paper: 0)",
    ),
    "--light-tv-weight": (
        "refine.light_tv_weight",
        finite_float,
        "weight of the smoothness prior on the estimated light "
        "(total variation of its log radiance; both methods; 0 turns it off)",
    ),
    "--normal-lr": (
        "refine.normal_lr",
        finite_float,
        "how fast refinement turns each Gaussian's shading normal by the rendering loss (both methods: the paper "
        "refines normals; 0 shades with the geometry's normals as they are)",
    ),
    "--predicted-normal-weight": (
        "refine.predicted_normal_weight",
        finite_float,
        "with a predictor that gives normal maps: weight of their angle to the rendered normals during refinement "
        "(default 1; 0: not used; a run whose 2D maps have no normals refines without them)",
    ),
    "--object-bounds": (
        "object_bounds",
        lambda v: tuple(finite_float(x) for x in v.replace(",", " ").split()),
        "captures without masks: the object region, 'x,y,z,r' (a sphere) or 'x0,y0,z0,x1,y1,z1' (a box) in world "
        "units (default: chosen automatically after geometry; see docs/data.md, captures without masks)",
    ),
    "--light-probe": (
        "light_probe",
        lambda v: os.path.abspath(os.path.expanduser(v)),
        "a known training light: an HDR lat-long map (.exr/.hdr) of the light the photos were "
        "taken in, in the capture's world frame (a light probe); the PBR variants shade with it instead of "
        "estimating the light (default: estimate it)",
    ),
    "--seed": ("seed", int, "random seed (default 0)"),
    "--refine-seed": ("refine_seed", int, "the refinement's own seed (default: --seed)"),
    "--downscale": (
        "downscale",
        finite_float,
        "shrink images by this factor on load (default: photos whose long side exceeds the "
        "preset's working size, test 128 / demo 256 / paper 800 px, are brought to it; 1 keeps them)",
    ),
    "--max-gaussians": (
        "geometry.max_gaussians",
        int,
        "cap on the Gaussians densification may grow to (default: the preset's; "
        "lower it when a GPU runs out of memory)",
    ),
    "--device": ("device", str, DEVICE_HELP),
    "--backend": ("backend", str, BACKEND_HELP),
}
# the setting flags a user command shows in its help (the others are research settings: `--set`)
USER_SETTING_FLAGS = ("--downscale", "--object-bounds", "--device", "--backend")
FLAG_OF_SETTING = {
    setting: flag if flag in USER_SETTING_FLAGS else f"--set {setting}"
    for flag, (setting, _, _) in SETTING_FLAGS.items()
}
FLAG_OF_SETTING.update(
    {
        "preset": "--preset",
        "method": "--method",
        "without": "--without",
        "visibility": "--set shadows",
        "objects": "--objects",
        "severity": "--severity",
        "batch_size": "--batch-size",
        "ensemble_size": "--ensemble-size",
        "steps": "--steps",
        "predictor": "--predictor",
        "basecolor_encoding": "--basecolor-encoding",
        "relight_envs": "--relight-env",
        "out": "--out",
        "resolution": "--resolution",
        "train_views": "--views",
        "test_views": "--test-views",
        "spp": "--spp",
        "env_height": "--env-height",
        "asset": "--asset",
        "assets": "--assets",
        "placement": "--placement",
        "workers": "--workers",
        "address": "--address",
        "cpus_per_object": "--cpus-per-object",
        "gpus_per_object": "--gpus-per-object",
        "weights": "--weights",
        "normals_weights": "--normals-weights",
        "export.faces": "--faces",
        "export.texture_size": "--texture-resolution",
        "export.frame": "--frame",
        "export.asset_normals": "--asset-normals",
        "export.bake": "--bake",
    }
)


VARIANT_HELP = "which asset of the run (default: full when the run has it, else the one it has, e.g. no-prior)"


def add_compute_arguments(parser) -> None:
    """--device and --backend, for the commands that compute outside a pipeline (geometry, relight, eval, export)."""
    parser.add_argument("--device", default="auto", help=DEVICE_HELP)
    parser.add_argument("--backend", default="auto", help=BACKEND_HELP)


def add_run_arguments(parser) -> None:
    """What `run` and `batch` take besides the method: the predictor, its options and the variants."""
    from matspray.predictors.kinds import add_run_option_flags, predictor_usage

    parser.add_argument(
        "--predictor",
        default="auto",
        metavar="SPEC",
        help=f"2D material maps: {predictor_usage()}, or none (no maps: only the no-prior variant); default auto: "
        "simulated where the dataset has ground-truth maps, else none",
    )
    parser.add_argument(
        "--variant",
        choices=VARIANT_NAMES,
        nargs="+",
        default=None,
        help="method variants to refine (the paper's ablations, and no-prior: the baseline without a 2D prior); "
        "default: full, or no-prior with --predictor none",
    )
    add_run_option_flags(parser)  # the predictors' options `run` offers (`matspray.predictors.kinds`)


def predictor_options_from_args(args) -> dict:
    """PredictorOptions fields from the predictors' flags given."""
    from matspray.predictors.kinds import run_options_from_args

    return run_options_from_args(args)


def given(args, flags) -> list[str]:
    """Which of `flags` the command line gave (a flag left at None, [] or off was not)."""
    return [flag for flag in flags if getattr(args, flag.lstrip("-").replace("-", "_")) not in (None, [], False)]


def refuse(flags: list[str], what: str) -> None:
    """Flags that nothing would read are refused, not ignored: '<flags> is|are <what>'."""
    if flags:
        from matspray.errors import ConfigError

        raise ConfigError(f"{' and '.join(flags)} {'is' if len(flags) == 1 else 'are'} {what}")


def hidden_alias(parser, flag: str, dest: str, **kwargs) -> None:
    """An old name of a flag: it still parses (into `dest`), shown in no help."""
    parser.add_argument(flag, dest=dest, help=argparse.SUPPRESS, default=argparse.SUPPRESS, **kwargs)


COMPUTE_FLAGS = ("--device", "--backend")


def add_method_arguments(parser, presets=PRESETS, default_preset: str = "demo", visible=None) -> None:
    """--preset, --method, --without, and every setting flag. A user command names the flags its help shows
    (`visible`); the others parse, hidden (their settings are reached by `--set`, `add_set_argument`), as does
    --shadows (`--set shadows=on`). `visible=None` shows every setting flag: the benchmarks' parsers."""
    parser.add_argument(
        "--preset",
        choices=presets,
        default=default_preset,
        help=(
            f"sizes: test (tiny, for CI), demo (128 px, 2 CPU cores), paper (512 px, one GPU); default {default_preset}"
        ),
    )
    parser.add_argument(
        "--method",
        choices=METHODS,
        default="matspray",
        help="matspray (default): the paper plus our measured additions; paper: exactly the paper's method "
        "(and its released code where the text is silent)",
    )
    group = parser.add_argument_group(
        "method settings (default: the method's; each matspray addition has its own switch)"
    )
    group.add_argument(
        "--without",
        nargs="+",
        choices=ADDITION_NAMES,
        default=(),
        metavar="ADDITION",
        help=f"switch single additions of matspray off: {', '.join(ADDITION_NAMES)}",
    )
    group.add_argument("--shadows", choices=("on", "off"), help=argparse.SUPPRESS)
    for flag, (_, _, text) in SETTING_FLAGS.items():
        shown = text if visible is None or flag in visible else argparse.SUPPRESS
        group.add_argument(flag, metavar=flag.lstrip("-").split("-")[-1].upper(), help=shown)


def method_settings_from_args(args) -> dict:
    """{dotted setting: value} for the flags the user gave (parsed to the setting's type)."""
    from matspray.errors import SettingError
    from matspray.method.config import shadow_maps

    settings = {}
    for flag, (setting, parse, _) in SETTING_FLAGS.items():
        text = getattr(args, flag.lstrip("-").replace("-", "_"), None)
        if text is None:
            continue
        try:
            settings[setting] = parse(text)
        except NotFinite as exc:
            raise SettingError(setting, str(exc)) from None
        except (ValueError, KeyError):
            raise SettingError(setting, f"cannot read {text!r}") from None
    if args.shadows is not None:
        settings["visibility"] = shadow_maps(args.preset) if args.shadows == "on" else None
    return settings


def build_config_from_args(args, **fixed):
    """The run's PipelineConfig from the parsed flags and `--set` (`fixed`: settings the command sets itself)."""
    from matspray.cli.settings import settings_from_overrides
    from matspray.method.config import build_config

    named = settings_from_overrides(getattr(args, "overrides", None), args.preset)
    return build_config(
        args.preset, args.method, tuple(args.without), **{**method_settings_from_args(args), **named, **fixed}
    )


# where a command's own flag sets a setting whose name means a research setting elsewhere (predict's --seed is the
# predictor's, a run's `--set seed` the pipeline's)
COMMAND_FLAGS = {"predict": {"seed": "--seed", "processing_resolution": "--processing-resolution"}}


def flag_message(error, command: str | None = None, flags=None) -> str:
    """An error's one-line message; a SettingError names the flag of `command` that set the setting (`--set KEY`
    for a research setting). `flags`: the options `command` shows, when known: a message never points at a flag the
    command lacks (`--set downscale` in a command without --downscale is no setting of it, not 'use --downscale')."""
    own = getattr(error, "flag", None)  # settings.OwnFlagError: --set KEY of a setting that a flag sets
    if own is not None and flags is not None and own not in flags:
        return f"--set {error.key}: `matspray {command}` has no such setting ({own} is a flag of `matspray run`)"
    setting = getattr(error, "setting", None)
    if setting is None:
        return str(error)
    flag = {**FLAG_OF_SETTING, **COMMAND_FLAGS.get(command, {})}.get(setting, f"--set {setting}")
    if flags is not None and flag.split()[0] not in flags:
        flag = f"--set {setting}" if "--set" in flags else setting
    return f"{flag}: {error.problem}"


def shown_flags(parser) -> set[str]:
    """The options a command's parser shows in its help (hidden old names are not pointed at)."""
    return {s for a in parser._actions if a.help != argparse.SUPPRESS for s in a.option_strings}
