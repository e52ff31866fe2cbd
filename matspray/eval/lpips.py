"""LPIPS v0.1 with the AlexNet backbone (Zhang et al. 2018), from a local weights file.

The network, as the reference `lpips` package defines it:
  input in [-1, 1]  ->  (x - shift) / scale, shift (-.030, -.088, -.188), scale (.458, .448, .450)
  AlexNet `features` (torchvision layout), tapping the five ReLU outputs:
      conv 11x11 /4 pad 2 (64)  -> ReLU [tap 1] -> maxpool 3/2
      conv  5x5     pad 2 (192) -> ReLU [tap 2] -> maxpool 3/2
      conv  3x3     pad 1 (384) -> ReLU [tap 3]
      conv  3x3     pad 1 (256) -> ReLU [tap 4]
      conv  3x3     pad 1 (256) -> ReLU [tap 5]
  per tap: unit-normalise along channels (f / (||f|| + 1e-10)), squared difference of the two
  images, 1x1 linear head with non-negative weights and no bias, mean over space; sum of the taps.

Weights, in the order `load_lpips` tries them:
1. an .npz file given by the caller or $MATSPRAY_LPIPS_WEIGHTS (`AlexNet_0/Conv_{i}/{kernel,bias}`,
   `NetLinLayer_{i}/Conv_0/kernel`, kernels HWIO: height, width, in, out; torch's conv2d wants OIHW, so
   they are transposed once on load);
2. the official `lpips` package, when it imports and its weights are already on disk;
3. torchvision's AlexNet checkpoint in torch's hub cache (where the `lpips` package and torchvision keep
   it) with the five linear heads that ship beside this module (`lpips_heads_v0.1.npz`, from LPIPS,
   BSD-2-Clause; THIRD_PARTY_NOTICES.md). `python -m matspray.eval.lpips --download` fetches that
   checkpoint once. Nothing here downloads on its own: without the checkpoint, evaluation reports LPIPS
   as unavailable and says in one line how to get it.

AlexNet's convolutions do not ship: they would be three times the size of everything else in the package,
and the standard place for them is torch's cache, which other tools on the machine share (docs/lpips.md).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Protocol

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from matspray.errors import DataError, file_error
from matspray.metrics import unit_image_pair

WEIGHTS_ENV = "MATSPRAY_LPIPS_WEIGHTS"
WEIGHTS_NAME = "lpips_alexnet_v0.1.npz"
HEADS_FILE = Path(__file__).with_name("lpips_heads_v0.1.npz")  # package data
# torchvision's ImageNet AlexNet, the backbone LPIPS v0.1 was calibrated on; the name's suffix is its sha256 prefix
ALEXNET_FILE = "alexnet-owt-7be5be79.pth"
ALEXNET_HASH = "7be5be79"
ALEXNET_URL = f"https://download.pytorch.org/models/{ALEXNET_FILE}"
ALEXNET_MB = 244
ALEXNET_LAYERS = (0, 3, 6, 8, 10)  # indices of the five convolutions in torchvision's `features`
DOWNLOAD_HINT = "python -m matspray.eval.lpips --download"

INPUT_SHIFT = (-0.030, -0.088, -0.188)
INPUT_SCALE = (0.458, 0.448, 0.450)
NORMALISE_EPS = 1e-10
# (kernel size, stride, padding, in channels, out channels, max-pool 3/2 before the conv)
ALEXNET_CONVS = (
    (11, 4, 2, 3, 64, False),
    (5, 1, 2, 64, 192, True),
    (3, 1, 1, 192, 384, True),
    (3, 1, 1, 384, 256, False),
    (3, 1, 1, 256, 256, False),
)
MIN_SIZE = 31  # smallest side for which both max-pools still have a 3x3 window to pool


class PerceptualMetric(Protocol):
    """What the evaluation needs from an LPIPS implementation."""

    source: str

    def distance(self, pred: Tensor, target: Tensor) -> float: ...  # [H, W, 3] in [0, 1] each


# ------------------------------------------------------------------------------------------ the network
def unit_normalise(features: Tensor, eps: float = NORMALISE_EPS) -> Tensor:  # [B, C, h, w] -> same
    return features / (features.square().sum(dim=1, keepdim=True).sqrt() + eps)


class LPIPS(nn.Module):
    """LPIPS v0.1 (AlexNet) as pure torch; weights are buffers, so `.to(device)` moves it whole."""

    def __init__(self, kernels: list[Tensor], biases: list[Tensor], heads: list[Tensor], source: str = "given weights"):
        # kernels[i] [O, I, k, k] (OIHW), biases[i] [O], heads[i] [1, C_i, 1, 1]
        super().__init__()
        for i, (kernel, bias, head) in enumerate(zip(kernels, biases, heads, strict=True)):
            self.register_buffer(f"kernel{i}", kernel.float())
            self.register_buffer(f"bias{i}", bias.float())
            self.register_buffer(f"head{i}", head.float())
        self.register_buffer(
            "shift", torch.tensor(INPUT_SHIFT, device="cpu").view(1, 3, 1, 1)
        )  # built on the host, moved by distance()
        self.register_buffer("scale", torch.tensor(INPUT_SCALE, device="cpu").view(1, 3, 1, 1))
        self.source = source

    @classmethod
    def from_npz(cls, path) -> LPIPS:
        kernels, biases, heads = read_weights(path)
        return cls(kernels, biases, heads, source=f"matspray AlexNet LPIPS v0.1, weights {Path(path).resolve()}")

    @classmethod
    def from_torchvision(cls, checkpoint, heads=HEADS_FILE) -> LPIPS:
        kernels, biases = read_torchvision_alexnet(checkpoint)
        source = (
            f"matspray AlexNet LPIPS v0.1, torchvision's AlexNet {Path(checkpoint).resolve()} and the packaged heads"
        )
        return cls(kernels, biases, read_heads(heads), source=source)

    def features(self, x: Tensor) -> list[Tensor]:  # [B, 3, H, W] scaled input -> 5 x [B, C_i, h_i, w_i]
        taps = []
        for i, (_, stride, padding, _, _, pool_first) in enumerate(ALEXNET_CONVS):
            if pool_first:
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            kernel, bias = getattr(self, f"kernel{i}"), getattr(self, f"bias{i}")
            x = F.relu(F.conv2d(x, kernel, bias, stride=stride, padding=padding))
            taps.append(x)
        return taps

    def forward(self, image0: Tensor, image1: Tensor) -> Tensor:  # [B, 3, H, W] in [-1, 1] each -> [B]
        taps0 = self.features((image0 - self.shift) / self.scale)
        taps1 = self.features((image1 - self.shift) / self.scale)
        total = image0.new_zeros(image0.shape[0])
        for i, (f0, f1) in enumerate(zip(taps0, taps1)):
            difference = (unit_normalise(f0) - unit_normalise(f1)).square()  # [B, C_i, h, w]
            total = total + F.conv2d(difference, getattr(self, f"head{i}")).mean(dim=(1, 2, 3))
        return total

    @torch.no_grad()
    def distance(self, pred: Tensor, target: Tensor) -> float:  # [H, W, 3] in [0, 1] each
        x0, x1 = lpips_input_pair(pred, target)
        self.to(x0.device)
        return float(self(x0.to(self.kernel0.dtype), x1.to(self.kernel0.dtype))[0])


def lpips_input_pair(pred, target) -> tuple[Tensor, Tensor]:  # [H, W, 3] in [0, 1] -> 2 x [1, 3, H, W] in [-1, 1]
    pred, target = unit_image_pair(pred, target)
    height, width, channels = pred.shape
    if channels != 3:
        raise DataError(f"LPIPS compares RGB images [H, W, 3], got {channels} channel(s) (repeat a grey map 3 times)")
    if min(height, width) < MIN_SIZE:
        raise DataError(f"LPIPS (AlexNet) needs images of at least {MIN_SIZE}x{MIN_SIZE} pixels, got {height}x{width}")
    return _network_input(pred), _network_input(target)


def _network_input(image: Tensor) -> Tensor:  # [H, W, 3] in [0, 1] -> [1, 3, H, W] float32 in [-1, 1]
    return (image.permute(2, 0, 1)[None] * 2 - 1).float()


def read_arrays(path) -> dict[str, np.ndarray]:
    path = Path(path)
    if not path.is_file():
        hint = f"expected {WEIGHTS_NAME}: pass --lpips-weights PATH or set ${WEIGHTS_ENV}"
        raise file_error(path, "LPIPS weights file does not exist", hint)
    try:
        with np.load(path, allow_pickle=False) as archive:
            return {key: archive[key] for key in archive.files}
    except Exception as error:  # not a zip / not an npz
        raise file_error(path, f"cannot read LPIPS weights ({error})", "expected a numpy .npz archive") from error


def checked_array(path, arrays: dict, key: str, shape: tuple[int, ...], what: str = "LPIPS v0.1 AlexNet weights"):
    if key not in arrays:
        raise file_error(path, f"missing array '{key}'", f"not {what}")
    value = arrays[key]
    if tuple(value.shape) != shape:
        raise file_error(path, f"array '{key}' has shape {tuple(value.shape)}, expected {shape}")
    value = np.asarray(value, dtype=np.float32)
    if not np.isfinite(value).all():
        raise file_error(path, f"array '{key}' contains NaN or Inf")
    return value


def read_heads(path, arrays: dict | None = None) -> list[Tensor]:
    """The five linear heads [1, C_i, 1, 1] from an .npz holding `NetLinLayer_{i}/Conv_0/kernel` (1x1xCx1)."""
    arrays = read_arrays(path) if arrays is None else arrays
    heads = []
    for i, (_, _, _, _, c_out, _) in enumerate(ALEXNET_CONVS):
        head = checked_array(path, arrays, f"NetLinLayer_{i}/Conv_0/kernel", (1, 1, c_out, 1))
        if (head < 0).any():
            raise file_error(path, f"linear head {i} has negative weights", "LPIPS heads are non-negative")
        heads.append(torch.from_numpy(head.transpose(3, 2, 0, 1).copy()))
    return heads


def read_weights(path) -> tuple[list[Tensor], list[Tensor], list[Tensor]]:
    """Kernels (OIHW), biases and heads [1, C, 1, 1] from an LPIPS AlexNet .npz (HWIO kernels)."""
    arrays = read_arrays(path)
    kernels, biases = [], []
    for i, (k, _, _, c_in, c_out, _) in enumerate(ALEXNET_CONVS):
        kernel = checked_array(path, arrays, f"AlexNet_0/Conv_{i}/kernel", (k, k, c_in, c_out))  # HWIO
        kernels.append(torch.from_numpy(kernel.transpose(3, 2, 0, 1).copy()))  # OIHW
        biases.append(torch.from_numpy(checked_array(path, arrays, f"AlexNet_0/Conv_{i}/bias", (c_out,))))
    return kernels, biases, read_heads(path, arrays)


def read_torchvision_alexnet(path) -> tuple[list[Tensor], list[Tensor]]:
    """Kernels (OIHW) and biases of the five convolutions of torchvision's AlexNet checkpoint (a state dict)."""
    path = Path(path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # truncated download, not a torch file
        raise file_error(
            path, f"cannot read AlexNet weights ({type(error).__name__})", f"delete it and run {DOWNLOAD_HINT}"
        ) from error
    if not isinstance(state, dict):
        raise file_error(path, "is not a state dict", f"delete it and run {DOWNLOAD_HINT}")
    arrays = {key: value.numpy() for key, value in state.items() if isinstance(value, Tensor)}
    kernels, biases = [], []
    for layer, (k, _, _, c_in, c_out, _) in zip(ALEXNET_LAYERS, ALEXNET_CONVS):
        what = "torchvision's AlexNet checkpoint"
        kernels.append(
            torch.from_numpy(checked_array(path, arrays, f"features.{layer}.weight", (c_out, c_in, k, k), what))
        )
        biases.append(torch.from_numpy(checked_array(path, arrays, f"features.{layer}.bias", (c_out,), what)))
    return kernels, biases


# ------------------------------------------------------------------------------------------ the official package
class OfficialLPIPS:
    """The reference `lpips.LPIPS(net='alex', version='0.1')`, behind the same `distance` call."""

    def __init__(self, network, version: str):
        self.network = network.eval()
        self.source = f"official lpips package {version} (AlexNet, v0.1)"

    @torch.no_grad()
    def distance(self, pred: Tensor, target: Tensor) -> float:  # [H, W, 3] in [0, 1] each
        x0, x1 = lpips_input_pair(pred, target)
        self.network.to(x0.device)
        return float(self.network(x0, x1).flatten()[0])


def official_lpips() -> tuple[OfficialLPIPS | None, str]:
    """The official package if it imports and all its weights are on disk, else (None, why not)."""
    try:
        import lpips  # noqa: PLC0415 (optional, and its torchvision may fail to import beside our torch)
    except Exception as error:  # ImportError, or torchvision's RuntimeError/AttributeError on import
        return None, f"official lpips package does not import ({type(error).__name__}: {error})"
    heads = Path(lpips.__file__).parent / "weights" / "v0.1" / "alex.pth"
    if not heads.is_file():
        return None, f"official lpips package has no {heads}"
    backbone = alexnet_checkpoint()
    if not backbone.is_file():
        return None, f"official lpips package: torchvision's AlexNet weights are not cached at {backbone}"
    try:
        network = lpips.LPIPS(net="alex", version="0.1", verbose=False)
    except Exception as error:
        return None, f"official lpips package failed to build ({type(error).__name__}: {error})"
    return OfficialLPIPS(network, getattr(lpips, "__version__", "?")), ""


# ------------------------------------------------------------------------------------------ lookup
def alexnet_checkpoint() -> Path:
    """Where torchvision and the `lpips` package keep AlexNet's weights: torch's hub cache ($TORCH_HOME)."""
    return Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_FILE


def unavailable_note() -> str:
    """The one line evaluation prints where no LPIPS weights are on this machine (after 'LPIPS: ')."""
    return (
        f"n/a: torchvision's AlexNet weights are not at {alexnet_checkpoint()}; get them once "
        f"({ALEXNET_MB} MB) with `{DOWNLOAD_HINT}`, or pass --lpips-weights FILE.npz (or set ${WEIGHTS_ENV})"
    )


def load_lpips(weights=None, allow_official: bool = True) -> tuple[PerceptualMetric | None, str]:
    """An LPIPS metric and where it comes from, or (None, one line saying how to get it).

    Order: `weights` when given (an error if it is unusable); the official `lpips` package when
    usable and `allow_official`; the file named by $MATSPRAY_LPIPS_WEIGHTS (an error if unusable);
    torchvision's AlexNet checkpoint in torch's hub cache with the packaged heads. Never downloads.
    """
    if weights is not None:
        model = LPIPS.from_npz(Path(weights))
        return model, model.source
    if allow_official:
        official, _ = official_lpips()
        if official is not None:
            return official, official.source
    from_env = os.environ.get(WEIGHTS_ENV)
    if from_env:
        try:
            model = LPIPS.from_npz(Path(from_env))
        except DataError as error:
            raise DataError(f"${WEIGHTS_ENV}: {error}") from error
        return model, model.source
    checkpoint = alexnet_checkpoint()
    if checkpoint.is_file():
        model = LPIPS.from_torchvision(checkpoint)
        return model, model.source
    return None, unavailable_note()


def download_alexnet(url: str = ALEXNET_URL, destination=None, hash_prefix: str | None = ALEXNET_HASH) -> Path:
    """Fetch torchvision's AlexNet checkpoint into torch's hub cache (or `destination`), its sha256 checked."""
    destination = Path(destination) if destination is not None else alexnet_checkpoint()
    if destination.is_file():
        return destination
    destination.parent.mkdir(parents=True, exist_ok=True)
    try:
        torch.hub.download_url_to_file(url, str(destination), hash_prefix=hash_prefix, progress=True)
    except Exception as error:  # no network (URLError), a wrong hash (RuntimeError), a full disk (OSError)
        raise DataError(
            f"{url}: download failed ({type(error).__name__}: {error}); offline, pass --lpips-weights FILE.npz "
            f"(or set ${WEIGHTS_ENV}) to eval instead"
        ) from error
    return destination


def main(argv: list[str] | None = None) -> int:
    import argparse
    import sys

    parser = argparse.ArgumentParser(
        prog="python -m matspray.eval.lpips", description="Which LPIPS weights evaluation uses, and fetching them."
    )
    parser.add_argument(
        "--download",
        action="store_true",
        help=f"fetch torchvision's AlexNet weights ({ALEXNET_MB} MB) into torch's cache",
    )
    args = parser.parse_args(argv)
    try:
        if args.download:
            print(f"AlexNet weights: {download_alexnet()}")
        metric, source = load_lpips()
    except DataError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(f"LPIPS: {source}")
    return 0 if metric is not None else 1


if __name__ == "__main__":
    raise SystemExit(main())
