"""The variants without 2D maps: no-prior (the paper's Table 1 baseline: materials from the PBR loss alone, no 2D maps
read) and photos-only (the same with a dielectric prior, what a run without a predictor makes by default)."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
import torch

from benchmarks.mapless_metallic import main as mapless_metallic
from matspray.errors import ConfigError
from matspray.eval.run_eval import evaluate_run
from matspray.method.asset import read_asset
from matspray.method.config import build_config, variant_refine_config
from matspray.method.pipeline import Pipeline
from matspray.method.refine.loop import RefineConfig, RefineInputs, refine
from matspray.presets import LABELS, MAPLESS, VARIANT_NAMES, asset_stage, get_variant, variants_for_maps
from matspray.rundir import RunDir
from tests.conftest import run_cli
from tests.reference_metrics import relighting_psnr
from tests.test_readers import blender_folder

DEFAULTS = RefineConfig()


def test_no_prior_and_photos_only_are_the_variants_that_need_no_maps():
    assert MAPLESS == ("no-prior", "photos-only") and set(MAPLESS) <= set(VARIANT_NAMES)
    for name in MAPLESS:
        variant = get_variant(name)
        assert variant.source == "free" and variant.learns_light and not variant.uses_maps
    assert [v.name for v in map(get_variant, VARIANT_NAMES) if v.dielectric_prior] == ["photos-only"]
    assert variants_for_maps(None, True) == ("full",) and variants_for_maps(None, False) == ("photos-only",)
    assert variants_for_maps(["full", "no-prior"], True) == ("full", "no-prior")
    assert variants_for_maps(["no-prior"], False) == ("no-prior",)
    with pytest.raises(
        ConfigError,
        match=r"^variant 'supervised' needs 2D material maps, and this run has none \(--predictor none\); "
        r"give a predictor \(files:DIR, marigold, \.\.\.\) or ask for no-prior / photos-only$",
    ):
        variants_for_maps(["no-prior", "supervised"], False)


def test_the_variants_without_maps_read_neither_the_lifted_values_nor_the_maps(tiny_object, tmp_path):
    config = build_config("test", predictor="simulated", **{"refine.iterations": 12})
    with Pipeline(tiny_object, tmp_path / "run", config, progress=False, log=lambda _: None) as pipeline:
        inputs = pipeline.refine_inputs()
    generator = torch.Generator().manual_seed(5)
    scrambled = replace(
        inputs,
        values=torch.rand(inputs.values.shape, generator=generator),
        targets=[torch.rand(t.shape, generator=generator) for t in inputs.targets],
    )
    for variant in MAPLESS:
        settings = variant_refine_config(config, variant)
        a, b = refine(inputs, settings, progress=False), refine(scrambled, settings, progress=False)
        torch.testing.assert_close(a.materials, b.materials, rtol=0, atol=0)
        assert all("material" not in record and "photo" in record for record in a.history)
        # and it trained: the grey it starts from moved
        assert (a.materials - 0.5).abs().max() > 1e-3
        # the metallic pull is photos-only's alone
        assert all(("metallic_prior" in record) == (variant == "photos-only") for record in a.history), variant


@pytest.mark.slow
def test_a_run_without_a_predictor_makes_the_photos_only_asset_and_no_prior_on_request(tiny_object, tmp_path, capsys):
    run = tmp_path / "run"
    config = build_config("test", predictor="none", **{"refine.iterations": 8})
    with Pipeline(tiny_object, run, config, progress=False, log=lambda _: None) as pipeline:
        assets = pipeline.run_all()
        assert list(assets) == ["photos-only"]
        assert RunDir(run).default_variant() == "photos-only"
        with pytest.raises(ConfigError, match="variant 'full' needs 2D material maps"):
            pipeline.refine("full")
        assets |= pipeline.run_all(["no-prior"])  # the paper's baseline, on the same geometry
    assert not (run / "materials2d").exists() and not (run / "asset").exists()
    assert (run / asset_stage("photos-only") / "asset.ply").exists() and (run / "lift" / "projected.pt").exists()
    # what commands take by default (relight, export, view, eval's report): the user's asset, not the baseline
    assert RunDir(run).asset_variants() == ["no-prior", "photos-only"]
    assert RunDir(run).default_variant() == "photos-only"
    metallic = {v: float(read_asset(run / asset_stage(v)).materials[:, 4].mean()) for v in MAPLESS}
    assert metallic["photos-only"] < metallic["no-prior"] - 0.1, metallic
    # without maps the lift only decides which Gaussians are seen: one ray per pixel, not the preset's 2 x 2
    lift_record = json.loads((run / "lift" / "stage.json").read_text())
    assert lift_record["settings"]["samples_per_side"] == 1 and lift_record["stats"]["samples_per_side"] == 1
    metrics = evaluate_run(run, progress=False)
    assert set(metrics["variants"]) == set(MAPLESS)
    assert "no 2D predictions: the run had none (--predictor none)" in metrics["notes"]
    assert list(metrics["table1"]) == [LABELS["no-prior"], LABELS["photos-only"]]
    for variant in MAPLESS:
        reference = relighting_psnr(run, tiny_object, variant)
        assert metrics["table1"][LABELS[variant]]["relighting"]["psnr"] == pytest.approx(reference, abs=1e-6)
    assert "| Relighting |" in (run / "eval" / "tables.md").read_text()
    # the development table of benchmarks.mapless_metallic reads both assets, as their stage records say they were made
    bench = tmp_path / "bench" / "objects" / "tiny"
    (bench / "runs").mkdir(parents=True)
    (bench / "data").symlink_to(tiny_object)
    (bench / "runs" / "run").symlink_to(run)
    mapless_metallic([str(tmp_path / "bench")])
    table = capsys.readouterr().out
    psnr = {v: metrics["variants"][v]["summary"]["relighting"]["psnr"] for v in MAPLESS}
    assert f"| no-prior | 8 | 0 | 0.5 | {metallic['no-prior']:.3f} | " in table, table
    pulled = f"photos-only | 8 | {DEFAULTS.metallic_prior_weight:g} | {DEFAULTS.metallic_prior_start:g}"
    assert f"| {pulled} | {metallic['photos-only']:.3f} | " in table, table
    assert f"| mean of 1 |  | {pulled} | {metallic['photos-only']:.3f} | " in table, table
    assert all(f" | {psnr[v]:.2f} | " in table for v in MAPLESS), (psnr, table)


def test_photos_only_settings_change_neither_no_prior_nor_its_fingerprint():
    plain = build_config("test", predictor="none")
    pulled = build_config(
        "test", predictor="none", **{"refine.metallic_prior_weight": 0.7, "refine.metallic_prior_start": 0.3}
    )
    for config in (plain, pulled):  # no-prior records them off: the paper's baseline, whatever photos-only's are
        settings = variant_refine_config(config, "no-prior")
        assert (settings.metallic_prior_weight, settings.metallic_prior_start) == (0.0, 0.5)
    assert variant_refine_config(pulled, "photos-only").metallic_prior_weight == 0.7
    assert variant_refine_config(pulled, "photos-only").metallic_prior_start == 0.3
    assert variant_refine_config(pulled, "no-prior") == variant_refine_config(plain, "no-prior")


def test_without_maps_the_lift_reads_the_views_at_the_size_geometry_trained_at(tiny_object, tmp_path):
    from matspray.data import load_scene

    width = load_scene(tiny_object).train[0].width
    for predictor, size in (("none", width // 2), ("simulated", width)):
        run = tmp_path / predictor
        config = build_config("test", predictor=predictor, **{"geometry.resolution": width // 2})
        with Pipeline(tiny_object, run, config, progress=False, log=lambda _: None) as pipeline:
            pipeline.refine_inputs()
        assert json.loads((run / "lift" / "stage.json").read_text())["stats"]["view_size"][0] == size


def test_cli_refuses_a_variant_that_needs_maps_without_a_predictor(tmp_path):
    # the refusal comes before any training, so a two-view dataset written here does (no Mitsuba object needed)
    data = blender_folder(tmp_path / "data")
    result = run_cli(
        "run", "--data", data, "--out", tmp_path / "run", "--preset", "test", "--predictor", "none", "--variant", "full"
    )
    assert result.returncode == 2 and "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "variant 'full' needs 2D material maps" in lines[0], result.stderr
    assert not (tmp_path / "run").exists()


@pytest.fixture
def capture_without_truth(tiny_object, tmp_path):
    """The tiny object as a capture would be: photos and cameras, no ground-truth material maps."""
    import shutil

    data = tmp_path / "capture"
    shutil.copytree(tiny_object, data)
    for path in data.rglob("*"):
        if any(part in path.name for part in ("_basecolor", "_roughness", "_metallic")):
            path.unlink()
    return data


def test_the_default_predictor_on_a_dataset_without_ground_truth_is_none(capture_without_truth, tmp_path):
    said = []
    config = build_config("test", predictor="auto", **{"refine.iterations": 4})
    with Pipeline(capture_without_truth, tmp_path / "run", config, progress=False, log=said.append) as pipeline:
        assert pipeline.config.predictor == "none" and not pipeline.has_maps
        assert list(pipeline.run_all()) == ["photos-only"]
    assert said[0].startswith(
        "predictor: this dataset has no ground-truth maps, so the run makes the photos-only asset"
    )
    assert json.loads(json.dumps(pipeline.run.config()))["predictor"] == "none"  # config.yaml says what ran


def test_a_predictor_that_needs_ground_truth_is_refused_before_training(capture_without_truth, tmp_path, tiny_object):
    from matspray.errors import DataError

    with pytest.raises(DataError, match=r"no ground-truth basecolor/roughness/metallic maps for 6 of 6 views"):
        Pipeline(
            capture_without_truth,
            tmp_path / "run",
            build_config("test", predictor="simulated:harsh"),
            progress=False,
            log=lambda _: None,
        )
    assert not (tmp_path / "run").exists()
    with Pipeline(
        tiny_object, tmp_path / "synth", build_config("test", predictor="auto"), progress=False, log=lambda _: None
    ) as pipeline:
        assert pipeline.config.predictor == "simulated"  # benchmarks: the synth object's true maps, degraded


def test_free_materials_learn_for_every_gaussian_a_view_shows_however_small_its_share():
    # `min_coverage` spares the merger's work on slivers of a view; a free per-Gaussian parameter costs nothing to read,
    # so none is left at its uninformed start: here no Gaussian reaches the (huge) threshold, and the seen ones learn
    from tests.scenes import lift_material_scene, material_scene

    gaussians, normals, _, views, maps = material_scene()
    lifted = lift_material_scene(gaussians, views, maps)
    kept = gaussians.subset(lifted.kept)
    bounds = torch.tensor([[-1.2] * 3, [1.2] * 3])
    inputs = RefineInputs(kept, normals[lifted.kept], lifted.values, lifted.seen, views, maps, bounds)
    config = RefineConfig(iterations=30, envmap_height=4, light_warmup=0, variant="no-prior", min_coverage=1e9)
    materials = refine(inputs, config, progress=False).materials
    moved = (materials - 0.5).abs().amax(-1) > 1e-4  # the free logits start at 0: grey 0.5
    assert float(moved.float().mean()) > 0.95, float(moved.float().mean())


def test_photos_only_can_start_its_base_colour_from_the_gaussians_own_colours():
    # refine.basecolor_start="photos": the free base colour starts at each Gaussian's view-independent colour (its
    # SH DC term) instead of grey; refinement then trains from there (0 steps: the start as it is)
    from matspray.errors import SettingError
    from matspray.render.shade.sh import rgb_to_sh_dc
    from tests.scenes import lift_material_scene, material_scene

    gaussians, normals, _, views, maps = material_scene()
    lifted = lift_material_scene(gaussians, views, maps)
    kept = gaussians.subset(lifted.kept)
    colours = torch.rand(len(kept), 3, generator=torch.Generator().manual_seed(3)) * 0.9 + 0.05
    kept.sh = kept.sh.clone()
    kept.sh[:, 0] = rgb_to_sh_dc(colours)
    bounds = torch.tensor([[-1.2] * 3, [1.2] * 3])
    inputs = RefineInputs(kept, normals[lifted.kept], lifted.values, lifted.seen, views, maps, bounds)
    for start, expected in (("photos", colours), ("grey", torch.full_like(colours, 0.5))):
        config = RefineConfig(
            iterations=0, envmap_height=4, light_warmup=0, variant="photos-only", basecolor_start=start
        )
        materials = refine(inputs, config, progress=False).materials
        assert torch.allclose(materials[:, :3], expected, atol=1e-5), start
        assert torch.allclose(materials[:, 4], torch.full_like(materials[:, 4], DEFAULTS.metallic_prior_start))
    config = RefineConfig(iterations=0, envmap_height=4, variant="no-prior", basecolor_start="photos")
    assert torch.allclose(
        refine(inputs, config, progress=False).materials[:, :3], torch.tensor(0.5)
    )  # photos-only's own
    assert (
        variant_refine_config(build_config("test", **{"refine.basecolor_start": "photos"}), "no-prior").basecolor_start
        == "grey"
    )
    with pytest.raises(SettingError, match="unknown start 'paint'; choose one of grey, photos"):
        RefineConfig(basecolor_start="paint")
