import numpy as np
import pytest
import torch

from matspray.data.images import (
    PNG_LEVEL,
    SCRATCH_PNG_LEVEL,
    linear_to_srgb,
    read_image,
    read_raw,
    resize,
    srgb_to_linear,
    write_image,
    write_raw,
)
from matspray.errors import DataError


def test_srgb_round_trip_within_1e6():
    x = torch.linspace(0.0, 1.0, 100001, dtype=torch.float64)
    assert (linear_to_srgb(srgb_to_linear(x)) - x).abs().max() < 1e-6
    assert (srgb_to_linear(linear_to_srgb(x)) - x).abs().max() < 1e-6


def test_srgb_curve_known_values():
    # the exact piecewise curve: linear segment below 0.04045, and 0.5 sRGB is 0.2140 linear
    assert float(srgb_to_linear(torch.tensor(0.04045))) == pytest.approx(0.04045 / 12.92)
    assert float(srgb_to_linear(torch.tensor(0.5))) == pytest.approx(0.21404114, abs=1e-7)
    assert float(linear_to_srgb(torch.tensor(1.0))) == pytest.approx(1.0)


@pytest.mark.parametrize("bits,tol", [(8, 0.5 / 255 + 1e-7), (16, 0.5 / 65535 + 1e-7)])
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_png_round_trip(tmp_path, bits, tol, channels):
    values = torch.rand(7, 5, channels)
    write_raw(tmp_path / "a.png", values, bits=bits)
    back = read_raw(tmp_path / "a.png")
    assert back.shape == (7, 5, channels)
    assert (back - values).abs().max() <= tol


@pytest.mark.parametrize("bits", [8, 16])
def test_a_scratch_png_is_zlibs_fastest_level_and_holds_the_same_values(tmp_path, bits):
    noise = torch.rand(64, 48, 3, generator=torch.Generator().manual_seed(0)) / 8  # compressible: a gradient
    values = torch.linspace(0, 0.8, 64 * 48).reshape(64, 48, 1) + noise
    for level in (PNG_LEVEL, SCRATCH_PNG_LEVEL):
        write_raw(tmp_path / f"{level}.png", values, bits=bits, png_level=level)
    assert torch.equal(read_raw(tmp_path / f"{PNG_LEVEL}.png"), read_raw(tmp_path / f"{SCRATCH_PNG_LEVEL}.png"))
    sizes = [(tmp_path / f"{level}.png").stat().st_size for level in (PNG_LEVEL, SCRATCH_PNG_LEVEL)]
    assert sizes[0] != sizes[1]  # the level reached zlib


def test_png_image_with_alpha_is_srgb_decoded(tmp_path):
    rgb = torch.rand(4, 6, 3)
    alpha = torch.rand(4, 6)
    write_image(tmp_path / "x.png", rgb, alpha, bits=16)
    rgb2, alpha2 = read_image(tmp_path / "x.png")
    assert (alpha2 - alpha).abs().max() < 1e-4
    assert (rgb2 - rgb).abs().max() < 2e-4  # 16-bit quantisation in sRGB space, mapped back


@pytest.mark.parametrize(
    "suffix,bits,channels",
    [(".png", bits, channels) for bits in (8, 16) for channels in (1, 2, 3, 4)] + [(".jpg", 8, 1), (".jpg", 8, 3)],
)
def test_integer_files_decode_every_level_as_the_srgb_curve_does(tmp_path, suffix, bits, channels):
    # every stored level of the file's depth appears: the table that decodes them must give the curve's values,
    # colour channels decoded, an alpha channel only scaled (JPEG holds none)
    levels = 2**bits
    count = min(levels, 4096)
    stored = np.linspace(0, levels - 1, count).round().astype(np.int64)
    values = torch.from_numpy(np.stack([np.roll(stored, c * 7) for c in range(channels)], -1) / (levels - 1))
    path = tmp_path / f"a{suffix}"
    if suffix == ".jpg":
        from PIL import Image

        pixels = np.repeat((values[None] * 255).round().numpy().astype(np.uint8), 8, 0)
        Image.fromarray(pixels[..., 0] if channels == 1 else pixels).save(path, quality=100)
    else:
        write_raw(path, values[None].float(), bits=bits)
    raw = read_raw(path)
    rgb, alpha = read_image(path)
    colour = 1 if channels < 3 else 3
    expected = srgb_to_linear(raw[..., :colour]).expand(*raw.shape[:-1], 3)
    assert rgb.dtype == torch.float32 and rgb.shape == (*raw.shape[:-1], 3)
    assert (rgb - expected).abs().max() <= 6e-8  # one float32 step at 1 at most (the curve's power, vectorised)
    if channels in (2, 4):
        assert torch.equal(alpha, raw[..., -1])
    else:
        assert alpha is None


def test_exr_round_trip_is_exact(tmp_path):
    for channels in (1, 3, 4):
        values = torch.randn(9, 4, channels) * 100
        write_raw(tmp_path / f"a{channels}.exr", values)
        assert torch.equal(read_raw(tmp_path / f"a{channels}.exr"), values)


def test_hdr_round_trip_relative_precision(tmp_path):
    values = torch.rand(10, 20, 3) * torch.logspace(-2, 3, 20)[None, :, None]
    write_raw(tmp_path / "a.hdr", values)
    back = read_raw(tmp_path / "a.hdr")
    rel = (back - values).abs() / values.amax(-1, keepdim=True)
    assert rel.max() < 1.0 / 128  # RGBE keeps 8 bits of mantissa for the brightest channel


def test_hdr_reads_run_length_encoded_scanlines(tmp_path):
    # hand-built new-style RLE file: width 8, one row; each channel is one run of 8 equal bytes
    header = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 1 +X 8\n"
    row = bytes([2, 2, 0, 8]) + b"".join(bytes([128 + 8, v]) for v in (128, 64, 32, 129))
    (tmp_path / "rle.hdr").write_bytes(header + row)
    back = read_raw(tmp_path / "rle.hdr")
    expected = (np.array([128, 64, 32]) + 0.5) * 2.0 ** (129 - 136)
    assert np.allclose(back[0].numpy(), expected[None, :].repeat(8, 0))


def test_nan_in_exr_is_rejected(tmp_path):
    values = torch.ones(4, 4, 3)
    values[1, 2, 0] = float("nan")
    write_raw(tmp_path / "bad.exr", values)
    with pytest.raises(DataError, match=r"bad\.exr: holds 1 NaN or Inf"):
        read_raw(tmp_path / "bad.exr")


def test_missing_and_unsupported_files(tmp_path):
    with pytest.raises(DataError, match=r"nope\.png: file does not exist"):
        read_raw(tmp_path / "nope.png")
    (tmp_path / "a.tiff").write_bytes(b"xx")
    with pytest.raises(DataError, match="unsupported image type"):
        read_raw(tmp_path / "a.tiff")
    (tmp_path / "broken.png").write_bytes(b"not a png at all")
    with pytest.raises(DataError, match=r"broken\.png: cannot read image"):
        read_raw(tmp_path / "broken.png")


def test_no_temporary_files_left(tmp_path):
    write_raw(tmp_path / "a.png", torch.rand(3, 3, 3))
    assert [p.name for p in tmp_path.iterdir()] == ["a.png"]


def test_resize_area_preserves_mean_and_nearest_keeps_values():
    g = torch.Generator().manual_seed(0)  # the global generator's state depends on which tests ran before
    image = torch.rand(32, 48, 3, generator=g)
    small = resize(image, 16, 24)
    assert small.shape == (16, 24, 3)
    # antialiased bilinear weighs the border rows and columns differently from the inner ones; the box mean does not
    assert torch.allclose(small.mean((0, 1)), image.mean((0, 1)), atol=2e-3)
    assert torch.allclose(resize(image, 16, 24, mode="box").mean((0, 1)), image.mean((0, 1)), atol=1e-6)
    mask = (torch.rand(32, 48, generator=g) > 0.5).float()
    assert set(resize(mask, 8, 12, mode="nearest").unique().tolist()) <= {0.0, 1.0}


def test_a_resized_views_alpha_stays_a_coverage_that_masked_metrics_take():
    from matspray.data import Camera
    from matspray.data.scene import View
    from matspray.metrics import psnr

    alpha = torch.zeros(128, 128)
    alpha[20:100, 30:90] = 1.0
    assert float(resize(alpha, 41, 37).max()) > 1.0  # the filter's rounding, which the view must not keep
    camera = Camera(torch.tensor([[100.0, 0, 64], [0, 100.0, 64], [0, 0, 1]]), torch.eye(4), 128, 128)
    small = View("v", torch.rand(128, 128, 3), alpha, camera).resized(37, 41)
    assert 0.0 <= float(small.alpha.min()) and float(small.alpha.max()) == 1.0
    assert psnr(small.image, small.image.flip(0), small.alpha) < 100.0  # was refused: "mask: values must be ..."


@pytest.mark.parametrize("bits", [8, 16])
def test_truncated_and_corrupt_png_are_data_errors(tmp_path, bits):
    write_raw(tmp_path / "a.png", torch.rand(16, 16, 3), bits=bits)
    data = (tmp_path / "a.png").read_bytes()
    (tmp_path / "truncated.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match=r"truncated\.png: cannot read image"):
        read_raw(tmp_path / "truncated.png")
    corrupt = bytearray(data)
    corrupt[60:80] = bytes(20)  # zeros inside the compressed pixel data
    (tmp_path / "corrupt.png").write_bytes(bytes(corrupt))
    with pytest.raises(DataError, match=r"corrupt\.png: cannot read image"):
        read_raw(tmp_path / "corrupt.png")
