"""Marigold-IID through diffusers, with a tiny randomly initialised pipeline built and saved here
(no downloads): end to end through `matspray predict`, output unpacking, and every loading error."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

pytest.importorskip("diffusers")
pytest.importorskip("transformers")

from matspray.cli import main  # noqa: E402
from matspray.data import Camera, View, load_scene, write_blender  # noqa: E402
from matspray.errors import ConfigError, DataError  # noqa: E402
from matspray.predictors import PredictorOptions, make_predictor, predict_views, read_materials2d, read_predictor_info  # noqa: E402
from matspray.predictors.marigold import MarigoldConfig, MarigoldPredictor, load_pipeline, target_layout  # noqa: E402

APPEARANCE = {
    "target_names": ["albedo", "material"],
    "albedo": {"prediction_space": "srgb"},
    "material": {"prediction_space": "stack", "sub_target_names": ["roughness", "metallicity", None]},
    "roughness": {"prediction_space": "linear"},
    "metallicity": {"prediction_space": "linear"},
}
LIGHTING = {
    "target_names": ["albedo", "shading", "residual"],
    "albedo": {"prediction_space": "linear"},
    "shading": {"prediction_space": "linear"},
    "residual": {"prediction_space": "linear"},
}


def tiny_parts(folder, unet_in: int, unet_out: int) -> dict:
    """Tokenizer, text encoder, VAE, UNet and scheduler of a Marigold pipeline with a few thousand random weights."""
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

    vocab = folder.parent / f"vocab-{folder.name}"
    vocab.mkdir()
    (vocab / "vocab.json").write_text(json.dumps({"<|startoftext|>": 0, "<|endoftext|>": 1, "a</w>": 2, "b</w>": 3}))
    (vocab / "merges.txt").write_text("#version: 0.2\n")
    tokenizer = CLIPTokenizer(str(vocab / "vocab.json"), str(vocab / "merges.txt"), model_max_length=8)
    torch.manual_seed(0)
    text_encoder = CLIPTextModel(
        CLIPTextConfig(
            vocab_size=4,
            hidden_size=16,
            intermediate_size=16,
            num_hidden_layers=1,
            num_attention_heads=2,
            max_position_embeddings=8,
            bos_token_id=0,
            eos_token_id=1,
            pad_token_id=1,
        )
    )
    vae = AutoencoderKL(
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D",) * 2,
        up_block_types=("UpDecoderBlock2D",) * 2,
        block_out_channels=(8, 8),
        layers_per_block=1,
        latent_channels=4,
        norm_num_groups=4,
        sample_size=16,
    )
    unet = UNet2DConditionModel(
        sample_size=8,
        in_channels=unet_in,
        out_channels=unet_out,
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
        block_out_channels=(8, 16),
        layers_per_block=1,
        cross_attention_dim=16,
        attention_head_dim=2,
        norm_num_groups=4,
    )
    scheduler = DDIMScheduler(num_train_timesteps=10, prediction_type="v_prediction", timestep_spacing="trailing")
    return dict(unet=unet, vae=vae, scheduler=scheduler, text_encoder=text_encoder, tokenizer=tokenizer)


def save_tiny_pipeline(folder, pipeline_class, unet_in: int, unet_out: int, **settings):
    """A diffusers Marigold pipeline of `tiny_parts` (2 denoising steps at 16 px) saved to `folder`."""
    parts = tiny_parts(folder, unet_in=unet_in, unet_out=unet_out)
    pipe = pipeline_class(**parts, default_denoising_steps=2, default_processing_resolution=16, **settings)
    pipe.save_pretrained(str(folder))
    return folder


def build_tiny_pipeline(folder):
    """A MarigoldIntrinsicsPipeline with the appearance model's targets and a few thousand random weights."""
    from diffusers import MarigoldIntrinsicsPipeline

    # image latent + 2 target latents in, 2 target latents out
    return save_tiny_pipeline(
        folder, MarigoldIntrinsicsPipeline, 12, 8, prediction_type="intrinsics", target_properties=APPEARANCE
    )


def build_tiny_normals_pipeline(folder):
    """A MarigoldNormalsPipeline with a few thousand random weights."""
    from diffusers import MarigoldNormalsPipeline

    # image latent + normals latent in, normals latent out
    return save_tiny_pipeline(folder, MarigoldNormalsPipeline, 8, 4, prediction_type="normals", use_full_z_range=True)


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    return build_tiny_pipeline(tmp_path_factory.mktemp("marigold") / "pipe")


@pytest.fixture(scope="module")
def normals_weights(tmp_path_factory):
    return build_tiny_normals_pipeline(tmp_path_factory.mktemp("marigold-normals") / "pipe")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    views = []
    for i in range(3):
        camera = Camera.look_at([3.0 * np.cos(i), 3.0 * np.sin(i), 0.5], [0, 0, 0], [0, 0, 1], 0.8, 20, 12)
        alpha = torch.zeros(12, 20)
        alpha[2:10, 4:16] = 1.0
        views.append(View(f"r_{i:03d}", torch.rand(12, 20, 3), alpha, camera))
    write_blender(root, {"train": views})
    return root


def quiet(_message):
    pass


def test_marigold_runs_end_to_end_through_predict(weights, dataset, tmp_path, capsys):
    run = tmp_path / "run"
    args = [
        "predict",
        "--data",
        str(dataset),
        "--out",
        str(run),
        "--predictor",
        "marigold",
        "--weights",
        str(weights),
        "--device",
        "cpu",
        "--batch-size",
        "2",
        "--steps",
        "1",
        "--ensemble-size",
        "3",
        "--seed",
        "4",
    ]
    assert main(args) == 0
    assert "wrote maps of 3 train view(s) from the marigold predictor" in capsys.readouterr().out
    views = load_scene(dataset).train
    maps = read_materials2d(run, views)
    info = read_predictor_info(run)
    assert (
        info["predictor"] == "marigold"
        and info["settings"]["ensemble_size"] == 3
        and info["targets"] == ["albedo", "material"]
    )
    # the same settings in process give the same maps (seeded), at the views' size, with a confidence map
    config = MarigoldConfig(weights=str(weights), device="cpu", batch_size=2, steps=1, ensemble_size=3, seed=4)
    direct = predict_views(views, MarigoldPredictor(config, notify=quiet), notify=quiet)
    for view in views:
        m = maps[view.name]
        assert m.basecolor.shape == (12, 20, 3) and m.confidence.shape == (12, 20)
        assert torch.allclose(m.basecolor, direct[view.name].basecolor, atol=3e-4)
        assert torch.allclose(m.roughness, direct[view.name].roughness, atol=1e-4)
        assert torch.allclose(m.metallic, direct[view.name].metallic, atol=1e-4)
        assert torch.allclose(m.confidence, direct[view.name].confidence, atol=1e-4)


def test_outputs_are_unpacked_by_target_properties(weights, dataset):
    """albedo (sRGB) -> linear base color; material R -> roughness, G -> metallic; image-major order."""
    views = load_scene(dataset).train[:2]
    predictor = MarigoldPredictor(MarigoldConfig(weights=str(weights), device="cpu"), notify=quiet)
    prediction = torch.zeros(2, 2, 3, 12, 20)  # [N, T, 3, H, W] as the pipeline orders it
    for i in range(2):
        prediction[i, 0] = torch.tensor([0.5, 0.25, 1.0])[:, None, None] * (i + 1) / 2  # albedo, sRGB
        prediction[i, 1, 0] = 0.1 + 0.5 * i  # roughness
        prediction[i, 1, 1] = 0.9 - 0.5 * i  # metallicity
        prediction[i, 1, 2] = 0.77  # unused channel
    calls = []

    def fake_pipe(images, **kwargs):
        calls.append((images.shape, kwargs))
        return SimpleNamespace(prediction=prediction.reshape(4, 3, 12, 20), uncertainty=None)

    predictor.pipe = _Callable(fake_pipe, APPEARANCE)
    out = predictor.predict(views)
    assert calls[0][0] == (2, 3, 12, 20) and calls[0][1]["output_type"] == "pt"
    from matspray.data import srgb_to_linear

    for i, view in enumerate(views):
        m = out[view.name]
        assert torch.allclose(m.basecolor[0, 0], srgb_to_linear(torch.tensor([0.5, 0.25, 1.0]) * (i + 1) / 2))
        assert torch.allclose(m.roughness, torch.full((12, 20), 0.1 + 0.5 * i))
        assert torch.allclose(m.metallic, torch.full((12, 20), 0.9 - 0.5 * i))
        assert m.confidence is None


class _Callable:
    def __init__(self, function, properties):
        self.function, self.target_properties, self.dtype = function, properties, torch.float32

    def __call__(self, *args, **kwargs):
        return self.function(*args, **kwargs)


def test_target_layout_needs_albedo_roughness_and_metallicity():
    assert target_layout(APPEARANCE) == {
        "albedo": (0, None, "srgb"),
        "roughness": (1, 0, "linear"),
        "metallicity": (1, 1, "linear"),
    }
    with pytest.raises(
        ConfigError, match="predicts albedo, residual, shading but not roughness, metallicity; .* appearance model"
    ):
        target_layout(LIGHTING)


def test_weights_errors(weights, tmp_path, monkeypatch):
    with pytest.raises(
        DataError,
        match="missing-folder: does not exist \\(the weights setting takes a pipeline folder or a hub id; on a machine",
    ):
        load_pipeline(str(tmp_path / "missing-folder"))
    with pytest.raises(DataError, match="is not a diffusers pipeline folder \\(no model_index.json\\)"):
        load_pipeline(str(tmp_path))
    other = tmp_path / "depth"
    other.mkdir()
    (other / "model_index.json").write_text(json.dumps({"_class_name": "MarigoldDepthPipeline"}))
    with pytest.raises(DataError, match="holds a MarigoldDepthPipeline, not a MarigoldIntrinsicsPipeline"):
        load_pipeline(str(other))
    from diffusers import MarigoldIntrinsicsPipeline

    def offline(*args, **kwargs):
        raise OSError("We couldn't connect to 'https://huggingface.co'")

    monkeypatch.setattr(MarigoldIntrinsicsPipeline, "from_pretrained", offline)
    with pytest.raises(
        ConfigError,
        match="cannot get Marigold weights 'prs-eth/marigold-iid-appearance-v1-1' from the Hugging Face hub "
        "\\(OSError\\); on a machine with network access run `hf download",
    ):
        make_predictor("marigold", PredictorOptions(device="cpu"))


def test_settings_errors(weights):
    with pytest.raises(ConfigError, match="ensemble_size: must be >= 1"):
        MarigoldConfig(ensemble_size=0)
    with pytest.raises(ConfigError, match="device: unknown device 'gpu7'"):
        make_predictor("marigold", PredictorOptions(weights=str(weights), device="gpu7"))
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="has no CUDA; use cpu"):
            make_predictor("marigold", PredictorOptions(weights=str(weights), device="cuda"))
    with pytest.raises(ConfigError, match="severity: does not apply to the marigold predictor"):
        make_predictor("marigold", PredictorOptions(weights=str(weights), severity=1.0))


# ------------------------------------------------------------------------------------------ normals
def test_marigold_normals_become_unit_camera_normals(weights, normals_weights, dataset, tmp_path):
    """The normals model's output: unit vectors in our camera axes ([H, W, 3], space "camera"), none off the object;
    through `matspray predict` they reach materials2d/ and come back the same."""
    views = load_scene(dataset).train
    config = MarigoldConfig(weights=str(weights), normals_weights=str(normals_weights), device="cpu", steps=1, seed=2)
    predictor = MarigoldPredictor(config, notify=quiet)
    out = predict_views(views, predictor, notify=quiet)
    for view in views:
        m = out[view.name]
        assert m.normal_space == "camera" and m.normals.shape == (12, 20, 3)
        lengths = m.normals.norm(dim=-1)
        on = view.alpha > 0
        assert torch.allclose(lengths[on], torch.ones_like(lengths[on]), atol=1e-5)
        assert bool((lengths[~on] == 0).all())
    assert predictor.describe()["settings"]["normals_weights"] == str(normals_weights)
    # the conversion from Marigold's axes (x right, y up, z to the viewer): y and z negated
    raw = torch.tensor([0.6, 0.0, 0.8])[:, None, None].expand(3, 12, 20)

    def fake_normals(images, **kwargs):
        return SimpleNamespace(prediction=raw[None].expand(len(images), -1, -1, -1))

    predictor.normals_pipe = _Callable(fake_normals, None)
    normals = predictor._normals(views[:1], 0)[0]
    assert torch.allclose(normals[5, 10], torch.tensor([0.6, 0.0, -0.8]))
    run = tmp_path / "run"
    args = ["predict", "--data", str(dataset), "--out", str(run), "--predictor", "marigold"]
    args += ["--weights", str(weights), "--normals-weights", str(normals_weights), "--device", "cpu", "--steps", "1"]
    assert main(args) == 0
    back = read_materials2d(run, views)
    assert read_predictor_info(run)["normal_space"] == "camera"
    assert all(back[v.name].normals.shape == (12, 20, 3) for v in views)


def test_normals_weights_errors(weights, tmp_path):
    from matspray.predictors.marigold import load_normals_pipeline

    with pytest.raises(DataError, match="holds a MarigoldIntrinsicsPipeline, not a MarigoldNormalsPipeline"):
        load_normals_pipeline(str(weights))
    with pytest.raises(DataError, match="does not exist .*hf download prs-eth/marigold-normals-v1-1"):
        MarigoldPredictor(MarigoldConfig(weights=str(weights), normals_weights=str(tmp_path / "nope"), device="cpu"))
