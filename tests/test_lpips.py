import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from numpy.lib.stride_tricks import sliding_window_view

from matspray.errors import DataError
from matspray.eval import lpips as lpips_module
from matspray.eval.lpips import LPIPS, OfficialLPIPS, load_lpips

WEIGHTS = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "lpips" / "lpips_alexnet_v0.1.npz"
needs_weights = pytest.mark.skipif(
    not WEIGHTS.is_file(), reason=f"LPIPS weights not found at {WEIGHTS} (shared test data is absent)"
)


def pattern(height: int, width: int, fx: float, fy: float, phase: float = 0.0) -> np.ndarray:
    """A smooth colour image [H, W, 3] in [0.1, 0.9], defined by formula (the same on every machine)."""
    y, x = np.meshgrid(np.linspace(0, 1, height), np.linspace(0, 1, width), indexing="ij")
    channels = [np.sin(2 * np.pi * (fx * x + fy * y) + phase + 2.1 * c) for c in range(3)]
    return (0.5 + 0.4 * np.stack(channels, axis=-1)).astype(np.float32)


def box_blur(image: np.ndarray, radius: int = 2) -> np.ndarray:
    padded = np.pad(image, ((radius, radius), (radius, radius), (0, 0)), mode="edge")
    return sliding_window_view(padded, (2 * radius + 1,) * 2, axis=(0, 1)).mean(axis=(-2, -1)).astype(np.float32)


def pairs():
    a = pattern(64, 64, 3.0, 1.0)
    fine = pattern(64, 64, 9.0, 5.0)
    noise = np.random.default_rng(7).standard_normal((64, 64, 3)).astype(np.float32)  # PCG64: stable stream
    return {
        "other_pattern": (a, pattern(64, 64, 1.0, 4.0, phase=0.5)),
        "blurred": (fine, box_blur(fine)),
        "contrast": (a, 0.5 * a + 0.25),
        "noise": (a, np.clip(a + 0.1 * noise, 0.0, 1.0)),
    }


# ------------------------------------------------------------------------------------------ independent reference
def reference_lpips(image0: np.ndarray, image1: np.ndarray, weights: Path) -> float:
    """LPIPS v0.1 AlexNet in float64 numpy, on HWC arrays with the file's HWIO kernels as they are."""
    w = np.load(weights)
    shift, scale = np.array([-0.030, -0.088, -0.188]), np.array([0.458, 0.448, 0.450])
    layers = [(4, 2, False), (1, 2, True), (1, 1, True), (1, 1, False), (1, 1, False)]  # stride, pad, pool first

    def conv(x, kernel, bias, stride, pad):  # [H, W, I], [kh, kw, I, O]
        x = np.pad(x, ((pad, pad), (pad, pad), (0, 0)))
        windows = sliding_window_view(x, kernel.shape[:2], axis=(0, 1))[::stride, ::stride]  # [h, w, I, kh, kw]
        return np.einsum("yxcij,ijco->yxo", windows, kernel) + bias

    def taps(image):
        x = ((2.0 * image.astype(np.float64) - 1.0) - shift) / scale
        out = []
        for i, (stride, pad, pool_first) in enumerate(layers):
            if pool_first:
                x = sliding_window_view(x, (3, 3), axis=(0, 1))[::2, ::2].max(axis=(-2, -1))
            kernel = w[f"AlexNet_0/Conv_{i}/kernel"].astype(np.float64)
            x = np.maximum(conv(x, kernel, w[f"AlexNet_0/Conv_{i}/bias"].astype(np.float64), stride, pad), 0.0)
            out.append(x)
        return out

    total = 0.0
    for i, (f0, f1) in enumerate(zip(taps(image0), taps(image1))):
        n0 = f0 / (np.sqrt((f0**2).sum(-1, keepdims=True)) + 1e-10)
        n1 = f1 / (np.sqrt((f1**2).sum(-1, keepdims=True)) + 1e-10)
        head = w[f"NetLinLayer_{i}/Conv_0/kernel"].astype(np.float64).reshape(-1)  # [C]
        total += float((((n0 - n1) ** 2) @ head).mean())
    return total


@pytest.fixture(scope="module")
def model():
    if not WEIGHTS.is_file():
        pytest.skip(f"LPIPS weights not found at {WEIGHTS} (shared test data is absent)")
    return LPIPS.from_npz(WEIGHTS)


@needs_weights
def test_identical_images_give_zero(model):
    a, _ = pairs()["other_pattern"]
    assert model.distance(torch.from_numpy(a), torch.from_numpy(a)) == 0.0


@needs_weights
def test_distance_is_symmetric_and_positive(model):
    a, b = (torch.from_numpy(x) for x in pairs()["blurred"])
    forward, backward = model.distance(a, b), model.distance(b, a)
    assert forward > 0.0
    assert forward == pytest.approx(backward, rel=1e-6)


@needs_weights
@pytest.mark.parametrize("name", ["other_pattern", "blurred", "contrast", "noise"])
def test_agrees_with_an_independent_numpy_forward_pass(model, name):
    a, b = pairs()[name]
    a, b = a[:, :57], b[:, :57]  # non-square: catches a swapped height/width
    expected = reference_lpips(a, b, WEIGHTS)
    assert model.distance(torch.from_numpy(a), torch.from_numpy(b)) == pytest.approx(expected, rel=2e-5)


# values computed once with this implementation (which agrees with the numpy reference above)
PINNED = {"other_pattern": 0.270571, "blurred": 0.0702434, "contrast": 0.0187804, "noise": 0.129543}


@needs_weights
@pytest.mark.parametrize("name", sorted(PINNED))
def test_pinned_values(model, name):
    a, b = pairs()[name]
    assert model.distance(torch.from_numpy(a), torch.from_numpy(b)) == pytest.approx(PINNED[name], rel=1e-4, abs=1e-6)


@needs_weights
def test_batched_forward_matches_single_images(model):
    stacked = [np.stack(p) for p in zip(*pairs().values())]  # 2 x [3, H, W, 3]
    x0, x1 = (torch.from_numpy(s).permute(0, 3, 1, 2) * 2 - 1 for s in stacked)
    batched = model(x0, x1)
    singles = [model.distance(torch.from_numpy(a), torch.from_numpy(b)) for a, b in pairs().values()]
    assert torch.allclose(batched, torch.tensor(singles), rtol=1e-5)


@needs_weights
def test_smallest_image_is_31_pixels(model):
    a = torch.from_numpy(pattern(31, 40, 2.0, 1.0))
    assert model.distance(a, a.flip(0)) > 0.0
    with pytest.raises(DataError, match="at least 31x31"):
        model.distance(a[:30], a[:30])
    with pytest.raises(DataError, match=r"RGB images \[H, W, 3\]"):
        model.distance(a[..., :1], a[..., :1])


# ------------------------------------------------------------------------------------------ weights file
def write_npz(path: Path, **changes) -> Path:
    arrays = dict(np.load(WEIGHTS))
    for key, value in changes.items():
        key = key.replace("__", "/")
        if value is None:
            del arrays[key]
        else:
            arrays[key] = value
    np.savez(path, **arrays)
    return path


@needs_weights
@pytest.mark.parametrize(
    "changes,message",
    [
        ({"AlexNet_0__Conv_2__bias": None}, "missing array 'AlexNet_0/Conv_2/bias'"),
        ({"AlexNet_0__Conv_0__kernel": np.zeros((64, 3, 11, 11), np.float32)}, r"has shape \(64, 3, 11, 11\)"),
        ({"NetLinLayer_1__Conv_0__kernel": -np.ones((1, 1, 192, 1), np.float32)}, "negative weights"),
    ],
)
def test_malformed_weights_are_rejected(tmp_path, changes, message):
    path = write_npz(tmp_path / "bad.npz", **changes)
    with pytest.raises(DataError, match=message):
        LPIPS.from_npz(path)


def test_unreadable_or_missing_weights_are_rejected(tmp_path):
    (tmp_path / "junk.npz").write_text("not a zip")
    with pytest.raises(DataError, match="junk.npz: cannot read LPIPS weights"):
        LPIPS.from_npz(tmp_path / "junk.npz")
    with pytest.raises(DataError, match="absent.npz: LPIPS weights file does not exist"):
        load_lpips(tmp_path / "absent.npz")


# ------------------------------------------------------------------------------------------ lookup
@pytest.fixture
def no_defaults(monkeypatch, tmp_path):
    monkeypatch.delenv(lpips_module.WEIGHTS_ENV, raising=False)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "empty_torch_home"))


def test_unavailable_lpips_is_none_with_one_line_saying_how_to_get_it(no_defaults, tmp_path):
    model, note = load_lpips(allow_official=False)
    checkpoint = tmp_path / "empty_torch_home" / "hub" / "checkpoints" / "alexnet-owt-7be5be79.pth"
    assert model is None and "\n" not in note
    assert note == (
        f"n/a: torchvision's AlexNet weights are not at {checkpoint}; get them once (244 MB) with "
        "`python -m matspray.eval.lpips --download`, or pass --lpips-weights FILE.npz (or set $MATSPRAY_LPIPS_WEIGHTS)"
    )


def test_environment_variable_naming_a_missing_file_is_an_error(no_defaults, monkeypatch, tmp_path):
    monkeypatch.setenv("MATSPRAY_LPIPS_WEIGHTS", str(tmp_path / "gone.npz"))
    with pytest.raises(DataError, match=r"\$MATSPRAY_LPIPS_WEIGHTS: .*gone.npz: LPIPS weights file does not exist"):
        load_lpips(allow_official=False)


@needs_weights
def test_weights_are_found_through_the_environment(no_defaults, monkeypatch):
    monkeypatch.setenv("MATSPRAY_LPIPS_WEIGHTS", str(WEIGHTS))
    model, source = load_lpips(allow_official=False)
    assert isinstance(model, LPIPS) and str(WEIGHTS.resolve()) in source


def test_no_lookup_reads_a_folder_beside_the_repository():
    text = Path(lpips_module.__file__).read_text()
    assert "shared" not in text and "parents[" not in text


def torchvision_checkpoint(path: Path, npz: Path) -> None:
    """A state dict in torchvision's AlexNet layout (features.{0,3,6,8,10}, OIHW) made from an LPIPS .npz."""
    arrays = np.load(npz)
    state = {}
    for i, layer in enumerate(lpips_module.ALEXNET_LAYERS):
        kernel = arrays[f"AlexNet_0/Conv_{i}/kernel"].transpose(3, 2, 0, 1).copy()
        state[f"features.{layer}.weight"] = torch.from_numpy(kernel)
        state[f"features.{layer}.bias"] = torch.from_numpy(arrays[f"AlexNet_0/Conv_{i}/bias"].copy())
    state["classifier.1.weight"] = torch.zeros(2, 2)  # the rest of the network, unused
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(state, path)


def test_packaged_heads_are_lpips_v0_1_alexnet_heads():
    heads = lpips_module.read_heads(lpips_module.HEADS_FILE)
    assert [tuple(h.shape) for h in heads] == [(1, c, 1, 1) for c in (64, 192, 384, 256, 256)]
    assert all(float(h.min()) >= 0 for h in heads)
    if WEIGHTS.is_file():  # the same arrays as the full weights file of the shared test data
        full_model = LPIPS.from_npz(WEIGHTS)
        for packaged, full in zip(heads, [getattr(full_model, f"head{i}") for i in range(5)]):
            assert torch.equal(packaged, full)


@needs_weights
def test_torchvision_checkpoint_in_torchs_cache_with_the_packaged_heads(no_defaults, tmp_path):
    checkpoint = tmp_path / "empty_torch_home" / "hub" / "checkpoints" / "alexnet-owt-7be5be79.pth"
    torchvision_checkpoint(checkpoint, WEIGHTS)
    model, source = load_lpips(allow_official=False)
    assert isinstance(model, LPIPS) and str(checkpoint) in source and "packaged heads" in source
    a, b = pairs()["blurred"]
    reference = LPIPS.from_npz(WEIGHTS).distance(torch.from_numpy(a), torch.from_numpy(b))
    assert model.distance(torch.from_numpy(a), torch.from_numpy(b)) == pytest.approx(reference, rel=1e-6)


def test_a_damaged_checkpoint_is_refused_in_one_line(no_defaults, tmp_path):
    checkpoint = lpips_module.alexnet_checkpoint()
    checkpoint.parent.mkdir(parents=True)
    checkpoint.write_bytes(b"half a download")
    with pytest.raises(DataError, match=r"alexnet-owt-7be5be79.pth: cannot read AlexNet weights .*--download\)$"):
        load_lpips(allow_official=False)
    torch.save({"features.0.weight": torch.zeros(3)}, checkpoint)
    with pytest.raises(DataError, match=r"array 'features.0.weight' has shape \(3,\), expected \(64, 3, 11, 11\)"):
        load_lpips(allow_official=False)


def test_download_fetches_once_into_torchs_cache_and_checks_the_hash(no_defaults, tmp_path, capsys):
    import hashlib

    source = tmp_path / "served.pth"
    source.write_bytes(b"checkpoint bytes")
    digest = hashlib.sha256(source.read_bytes()).hexdigest()
    target = lpips_module.download_alexnet(source.as_uri(), hash_prefix=digest[:8])
    assert target == lpips_module.alexnet_checkpoint() and target.read_bytes() == b"checkpoint bytes"
    source.write_bytes(b"changed")  # a second call finds the cached file and fetches nothing
    assert lpips_module.download_alexnet(source.as_uri(), hash_prefix="00000000").read_bytes() == b"checkpoint bytes"
    target.unlink()
    with pytest.raises(
        DataError, match=r"served.pth: download failed \(RuntimeError: .*; offline, pass --lpips-weights FILE.npz"
    ):
        lpips_module.download_alexnet(source.as_uri(), hash_prefix="00000000")
    assert not target.exists()
    with pytest.raises(DataError, match=r"download failed \(URLError"):
        lpips_module.download_alexnet((tmp_path / "absent.pth").as_uri())


def test_module_command_reports_the_source_or_the_note(no_defaults, monkeypatch, capsys):
    monkeypatch.setattr(sys.modules["matspray.eval.lpips"], "official_lpips", lambda: (None, "absent"))
    assert lpips_module.main([]) == 1
    assert capsys.readouterr().out.startswith("LPIPS: n/a: torchvision's AlexNet weights are not at ")


# ------------------------------------------------------------------------------------------ the official package
def fake_lpips_package(root: Path, body: str) -> None:
    package = root / "lpips"
    (package / "weights" / "v0.1").mkdir(parents=True)
    (package / "weights" / "v0.1" / "alex.pth").write_bytes(b"")
    (package / "__init__.py").write_text(body)


def test_official_package_that_fails_to_import_falls_back(no_defaults, monkeypatch, tmp_path):
    # what torchvision does beside a torch it was not built for
    fake_lpips_package(tmp_path, "raise RuntimeError('operator torchvision::nms does not exist')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "lpips", raising=False)
    assert lpips_module.official_lpips()[1].startswith(
        "official lpips package does not import (RuntimeError: operator torchvision::nms"
    )
    model, note = load_lpips()
    assert model is None and note.startswith("n/a: ")


def test_official_package_without_cached_backbone_is_not_used(no_defaults, monkeypatch, tmp_path):
    would_download = "class LPIPS:\n    def __init__(self, **kw):\n        raise AssertionError('would download')\n"
    fake_lpips_package(tmp_path, would_download)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "lpips", raising=False)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    assert "torchvision's AlexNet weights are not cached" in lpips_module.official_lpips()[1]
    model, note = load_lpips()
    assert model is None and note.startswith("n/a: ")


def test_official_package_is_preferred_and_called_with_inputs_in_minus_one_one(no_defaults, monkeypatch, tmp_path):
    fake_lpips_package(
        tmp_path,
        (
            "import torch\n__version__ = '9.9'\ncalls = []\n"
            "class LPIPS(torch.nn.Module):\n"
            "    def __init__(self, net, version, verbose):\n        super().__init__(); calls.append((net, version))\n"
            "    def forward(self, x0, x1):\n"
            "        calls.append((tuple(x0.shape), float(x0.min()), float(x0.max())))\n"
            "        return (x0 - x1).abs().mean().view(1, 1, 1, 1)\n"
        ),
    )
    (tmp_path / "torch_home" / "hub" / "checkpoints").mkdir(parents=True)
    (tmp_path / "torch_home" / "hub" / "checkpoints" / "alexnet-owt-7be5be79.pth").write_bytes(b"")
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "lpips", raising=False)
    model, source = load_lpips()
    assert isinstance(model, OfficialLPIPS) and source == "official lpips package 9.9 (AlexNet, v0.1)"
    white, black = torch.ones(32, 32, 3), torch.zeros(32, 32, 3)
    assert model.distance(white, black) == pytest.approx(2.0)
    calls = sys.modules["lpips"].calls
    assert calls == [("alex", "0.1"), ((1, 3, 32, 32), 1.0, 1.0)]
