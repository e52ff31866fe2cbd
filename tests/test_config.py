"""Run settings: presets and methods as data, `--method paper` switching every addition off, settings
errors that name the setting (library) or the flag (CLI), and the light prior."""

import argparse
import subprocess
import sys
from dataclasses import replace

import pytest
import torch
import yaml

from matspray import presets
from matspray.cli import build_parser
from matspray.errors import SettingError
from matspray.geometry.config import GeometryConfig
from matspray.method.config import (
    ADDITIONS,
    NORMAL_PRIOR_WEIGHT,
    PipelineConfig,
    build_config,
    shadow_maps,
    with_setting,
)
from matspray.method.lift import LiftConfig
from matspray.method.merger import MergerConfig, fill_unseen, prepare_values
from matspray.method.refine.loop import RefineConfig
from matspray.presets import VARIANT_NAMES
from matspray.render.shade.envmap import EnvironmentMap
from matspray.render.shade.latlong import irradiance_correlation, total_variation
from matspray.render.shade.visibility import VisibilityConfig
from matspray.rundir import RunDir
from tests.conftest import run_cli


def test_defaults_are_the_demo_preset_of_the_default_method():
    assert PipelineConfig() == build_config("demo")
    assert PipelineConfig().method == "matspray"
    prior = NORMAL_PRIOR_WEIGHT  # a run's default, where its 2D maps have normal maps; the stages alone default to 0
    assert build_config("demo").refine == RefineConfig(predicted_normal_weight=prior)
    assert build_config("demo").lift == LiftConfig() and RefineConfig().merger == MergerConfig()
    for preset in ("test", "demo", "paper"):  # the paper trains on its 2D model's normals for specular objects only
        ours, paper = build_config(preset), build_config(preset, "paper")
        assert ours.geometry.predicted_normal_weight == ours.refine.predicted_normal_weight == prior > 0
        assert paper.geometry.predicted_normal_weight == paper.refine.predicted_normal_weight == 0


def test_paper_method_sets_every_switch_as_the_paper_and_config_yaml_records_it(tmp_path):
    run = RunDir(tmp_path)
    run.write_config(build_config("test", "paper"))
    written = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert written["method"] == "paper"
    lift, refine = written["lift"], written["refine"]
    assert lift["visibility_threshold"] == 0.0  # every ray hit receives the pixel's value
    assert lift["footprint_sigmas"] == 1.0  # the released code's 1-sigma ellipsoid
    assert lift["min_support"] == 0.0  # every view that hit a Gaussian counts
    assert refine["merger"]["unseen"] == "mean"  # unseen views filled with the mean (released code)
    assert refine["merger"]["seen_input"] is False  # merger input: PE(position) + per-view values only
    assert (refine["merger"]["hidden"], refine["merger"]["layers"], refine["merger_lr"]) == (128, 3, 1e-3)
    assert refine["basecolor_loss"] == "l1" and refine["material_weight"] == 1.0
    assert refine["photo_weight"] == 2.0 and refine["photo_l1_weight"] == 0.8  # the released code's, as matspray
    assert refine["metallic_quantile"] == 0.5  # L1: the median of the views (matspray: 0.25, `metallic-quantile`)
    assert refine["light_warmup"] == 0 and refine["min_coverage"] == 0.0
    assert written["visibility"] is None  # no shadowing
    assert refine["light_tv_weight"] == 0.0 and refine["normal_prior_weight"] == 0.0  # no priors the paper names
    assert refine["predicted_normal_weight"] == 0.0 and written["geometry"]["predicted_normal_weight"] == 0.0
    assert lift["samples_per_side"] == 2  # presets keep their sizes
    assert build_config("paper", "paper").lift.samples_per_side == 16


def test_matspray_differs_from_paper_exactly_by_the_additions():
    paper, ours = build_config("demo", "paper"), build_config("demo")
    for addition in ADDITIONS:
        assert with_setting(ours, addition.setting, addition.paper) != ours, addition.name
    for addition in ADDITIONS:
        ours = with_setting(ours, addition.setting, addition.paper)
    assert ours == paper.__class__(**{**paper.__dict__, "method": "matspray"})


def test_single_additions_switch_off():
    config = build_config("demo", without=("light-warmup", "min-support"))
    assert config.refine.light_warmup == 0 and config.lift.min_support == 0.0
    assert config.refine.light_tv_weight > 0 and config.refine.min_coverage > 0  # the others stay on
    with pytest.raises(SettingError, match="unknown addition.*colour"):
        build_config("demo", without=("colour",))
    with pytest.raises(SettingError, match="^without: turns off additions of --method matspray; --method paper has"):
        build_config("demo", method="paper", without=("light-warmup",))  # was accepted, and changed nothing
    with pytest.raises(SettingError, match=r"^lift.min_support: --without min-support sets it too \(to 0.0\); give"):
        build_config("demo", without=("min-support",), **{"lift.min_support": 0.3})  # the setting won, silently
    assert build_config("demo", method="paper", **{"lift.min_support": 0.3}).lift.min_support == 0.3  # an override


def test_bad_settings_name_the_setting():
    with pytest.raises(SettingError, match=r"^lift.min_support: must be in \[0, 1\], got 2") as error:
        build_config("demo", **{"lift.min_support": 2})
    assert error.value.setting == "lift.min_support"
    with pytest.raises(SettingError, match="^refine.merger.unseen: unknown rule 'zero'; choose one of mask, mean"):
        build_config("demo", **{"refine.merger.unseen": "zero"})
    with pytest.raises(SettingError, match="^geometry.iterations: must be >= 1"):
        build_config("demo", **{"geometry.iterations": 0})
    with pytest.raises(SettingError, match="^method: unknown method 'exact'; choose one of matspray, paper"):
        build_config("demo", "exact")
    with pytest.raises(SettingError, match="^lift.colour: no such setting"):
        build_config("demo", **{"lift.colour": 1})


def test_the_presets_are_one_torch_free_table_that_every_stage_reads():
    """The command line, the stages' configs and the demo take their presets from `matspray.presets`, which
    imports no torch (so `--help` stays fast)."""
    probe = "import sys\nimport matspray.presets, matspray.cli.options\nprint('torch' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.strip() == "False", done.stderr
    tables = (presets.PRESET_SETTINGS, presets.GEOMETRY, presets.SHADOW_MAPS, presets.DEMO_SIZES, presets.WORKING_SIZE)
    assert all(tuple(table) == presets.PRESETS for table in tables)
    for name in presets.PRESETS:
        config = build_config(name)
        assert config.geometry == replace(
            GeometryConfig(preset=name, **presets.GEOMETRY[name]),
            predicted_normal_weight=config.geometry.predicted_normal_weight,
        )
        for stage, partial in presets.PRESET_SETTINGS[name].items():
            for setting, value in partial.items():
                assert getattr(getattr(config, stage), setting) == value, (stage, setting)
        assert shadow_maps(name) == VisibilityConfig(**presets.SHADOW_MAPS[name])
    assert build_config("demo").geometry.iterations == GeometryConfig().iterations == 3000  # demo: the defaults
    assert build_config("paper").geometry.iterations == 30000 and build_config("paper").refine.iterations == 10000
    run = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices["run"]
    choices = {action.dest: action.choices for action in run._actions}
    assert tuple(choices["without"]) == tuple(a.name for a in presets.ADDITIONS)  # the CLI offers the library's names
    assert tuple(choices["preset"]) == presets.PRESETS and tuple(choices["method"]) == presets.METHODS
    assert tuple(choices["variant"]) == VARIANT_NAMES


def test_cli_names_the_flag_and_lists_methods(tmp_path):
    result = run_cli("run", "--data", tmp_path, "--out", tmp_path / "run", "--method", "exact")
    assert (
        result.returncode == 2
        and "invalid choice: 'exact'" in result.stderr
        and "matspray" in result.stderr.splitlines()[-1]
        and "paper" in result.stderr.splitlines()[-1]
    )
    result = run_cli("run", "--data", tmp_path, "--out", tmp_path / "run", "--set", "lift.min_support=2")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip() == "matspray run: error: --set lift.min_support: must be in [0, 1], got 2.0"


def test_unseen_views_are_filled_with_the_mean_of_the_seen_views():
    values = torch.tensor([[[0.2] * 5, [0.6] * 5, [0.9] * 5]])  # [1, 3, 5]
    seen = torch.tensor([[True, True, False]])
    filled = fill_unseen(values, seen)
    assert torch.allclose(filled[0, 2], torch.full((5,), 0.4))
    assert torch.equal(filled[0, :2], values[0, :2])
    masked, all_seen = prepare_values(values, seen, "mean")
    assert all_seen.all() and torch.equal(masked, filled)
    masked, same = prepare_values(values, seen, "mask")
    assert torch.equal(same, seen) and float(masked[0, 2].abs().sum()) == 0.0


def test_total_variation_is_zero_for_a_constant_and_rises_with_noise():
    constant = torch.full((8, 16, 3), 0.3)
    assert float(total_variation(constant)) == 0.0
    noisy = constant + 0.1 * torch.randn(8, 16, 3, generator=torch.Generator().manual_seed(0))
    assert float(total_variation(noisy)) > 0.1


def test_total_variation_of_a_smooth_field_does_not_depend_on_resolution():
    # f = cos(theta): integral over the sphere of |df/dtheta| / 4 pi = pi / 4 (the phi term is 0)
    for height in (32, 128):
        theta = (torch.arange(height, dtype=torch.float64) + 0.5) / height * torch.pi
        field = torch.cos(theta)[:, None, None].expand(height, 2 * height, 1)
        assert float(total_variation(field)) == pytest.approx(torch.pi / 4, rel=2e-2)


def test_the_light_prior_lowers_the_total_variation_of_a_noisy_map():
    generator = torch.Generator().manual_seed(0)
    envmap = EnvironmentMap.from_tensor(torch.rand(8, 16, 3, generator=generator) * 2 + 0.1)
    from matspray.method.refine.loop import light_prior

    before = float(light_prior(envmap))
    optimizer = torch.optim.Adam(envmap.parameters(), lr=0.05)
    for _ in range(50):
        optimizer.zero_grad()
        light_prior(envmap).backward()
        optimizer.step()
    assert float(light_prior(envmap)) < 0.5 * before


def test_irradiance_correlation_is_one_for_a_scaled_copy_and_lower_for_a_rotated_light():
    from matspray.render.shade.lights import builtin_envmap

    sky = builtin_envmap("sky", 32)
    assert irradiance_correlation(sky, 3.0 * sky) == pytest.approx(1.0, abs=1e-9)
    assert irradiance_correlation(sky, sky.roll(16, dims=1)) < 0.9  # the sun on the other side


def test_cli_colmap_choices_match_the_library():
    from matspray.cli import datasets
    from matspray.data import sfm

    assert (datasets.MATCHERS, datasets.CAMERA_MODELS) == (sfm.MATCHERS, sfm.CAMERA_MODELS)


def test_shadows_are_off_by_default_and_on_with_the_presets_shadow_maps():
    import argparse

    from matspray.cli.options import add_method_arguments, build_config_from_args
    from matspray.cli.settings import add_set_argument
    from matspray.method.config import shadow_maps

    assert all(build_config(preset).visibility is None for preset in ("test", "demo", "paper"))
    assert (shadow_maps("test").rows, shadow_maps("paper").rows, shadow_maps("paper").resolution) == (4, 16, 512)
    parser = argparse.ArgumentParser()
    add_method_arguments(parser)
    add_set_argument(parser)
    for preset in presets.PRESETS:
        on = build_config_from_args(parser.parse_args(["--preset", preset, "--set", "shadows=on"]))
        assert on.visibility == shadow_maps(preset)
        off = build_config_from_args(parser.parse_args(["--preset", preset, "--set", "shadows=off"]))
        assert off.visibility is None
    with pytest.raises(SettingError, match="unknown preset 'huge'"):
        shadow_maps("huge")
