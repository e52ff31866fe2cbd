"""Image files in and out: exact sRGB curve, PNG (8/16 bit), OpenEXR, Radiance HDR; resampling.

In memory every image is a float32 tensor [H, W, C]. LDR files hold sRGB-encoded values (or linear
values for scalar maps such as roughness); EXR and HDR hold linear values.
"""

from __future__ import annotations

import functools
import os
import re
import struct
from pathlib import Path

import numpy as np
import OpenEXR
import png  # pypng: reads 16-bit colour PNGs, which Pillow reduces to 8 bit
import torch
import torch.nn.functional as F
from PIL import Image, ImageOps
from torch import Tensor

from matspray.errors import file_error
from matspray.files import HDR_SUFFIXES, atomic_target  # noqa: F401 - data modules import them from here too

LDR_SUFFIXES = (".png", ".jpg", ".jpeg")
# zlib's compression level of PNGs: Pillow's default for what users keep; its fastest for files that only this tool
# reads back (caches, scratch photos), where writing time counts more than size (docs/dev/real-captures.md, "The
# undistortion cache's PNGs")
PNG_LEVEL, SCRATCH_PNG_LEVEL = 6, 1
# what the decoders raise on a corrupt or truncated file (pypng's FormatError and ChunkError are
# Exception subclasses of their own; a truncated scanline shows up as an IndexError)
DECODER_ERRORS = (OSError, ValueError, SyntaxError, RuntimeError, EOFError, IndexError, KeyError)
# The most pixels a file may hold: Pillow's guard against decompression bombs (2 x Image.MAX_IMAGE_PIXELS, 179 MP),
# for every format. A header that claims more is damaged or hostile, and reading it would exhaust the memory.
MAX_PIXELS = 2 * Image.MAX_IMAGE_PIXELS


class TooLarge(ValueError):
    """A header that claims more than MAX_PIXELS pixels: its (width, height)."""

    def __init__(self, size: tuple[int, int]):
        super().__init__(f"{size[0]}x{size[1]} pixels")
        self.size = size


def check_pixels(width: int, height: int) -> None:
    if width * height > MAX_PIXELS:
        raise TooLarge((width, height))


def pillow_header_size(path: Path) -> tuple[int, int] | None:
    """(width, height) as a JPEG or PNG header claims it, read past Pillow's decompression-bomb guard (no pixel is
    decoded); None when the header cannot be read."""
    plugin = Image.OPEN.get(Image.registered_extensions().get(path.suffix.lower(), ""))
    try:
        with open(path, "rb") as handle:
            return tuple(plugin[0](handle, str(path)).size) if plugin else None
    except (*DECODER_ERRORS, struct.error):
        return None


def too_large_error(path: Path, error: Exception):
    """The one-line error of a header claiming too many pixels (TooLarge, or Pillow's DecompressionBombError)."""
    size = getattr(error, "size", None) or pillow_header_size(path)
    claimed = f"{size[0]}x{size[1]} pixels ({size[0] * size[1] / 1e6:.0f} megapixels)" if size else "too many pixels"
    return file_error(
        path,
        f"its header claims {claimed}, more than the {MAX_PIXELS / 1e6:.0f} megapixels an image may have",
        "the file is damaged, or too large to read: shrink it",
    )


# ------------------------------------------------------------------------------------------ sRGB
def srgb_to_linear(x: Tensor) -> Tensor:  # [...] -> [...]
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: Tensor) -> Tensor:  # [...] -> [...]
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-12) ** (1.0 / 2.4) - 0.055)


# ------------------------------------------------------------------------------------------ atomic writes
def _publish(tmp: Path, path: Path) -> None:
    os.replace(tmp, path)


def save_torch_atomic(obj, path) -> None:
    """`torch.save` that never leaves a half-written file at `path` (creates the folder)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = atomic_target(path)
    torch.save(obj, tmp)
    os.replace(tmp, path)


# ------------------------------------------------------------------------------------------ reading
def read_image(path, orient: bool = False) -> tuple[Tensor, Tensor | None]:
    """Read an image file as linear float32.

    Returns rgb [H, W, 3] (a single-channel file is broadcast to 3 channels) and alpha [H, W] or None.
    PNG/JPG are decoded from sRGB; EXR/HDR are read as stored. `orient`: turn photos upright as their
    EXIF orientation tag says (what a photo viewer shows).
    """
    path = Path(path)
    stored = _read_stored(path, orient)  # [H, W, C] as the file holds it
    if stored.dtype.kind == "u":  # 8- or 16-bit sRGB: decoded by a table of every stored level
        return split_alpha(torch.from_numpy(_decode_srgb_levels(stored)))
    rgb, alpha = split_alpha(torch.from_numpy(stored))
    if path.suffix.lower() in LDR_SUFFIXES:  # a rarer mode of an sRGB file, read as floats
        rgb = srgb_to_linear(rgb)
    return rgb, alpha


def split_alpha(values: Tensor) -> tuple[Tensor, Tensor | None]:  # [H, W, C] -> [H, W, 3], [H, W] | None
    channels = values.shape[-1]
    if channels == 1:
        return values.expand(-1, -1, 3).contiguous(), None
    if channels == 2:  # grey + alpha
        return values[..., :1].expand(-1, -1, 3).contiguous(), values[..., 1]
    if channels == 3:
        return values, None
    return values[..., :3].contiguous(), values[..., 3].contiguous()


def read_raw(path, orient: bool = False) -> Tensor:
    """Read stored values without colour decoding: [H, W, C] float32, LDR scaled to [0, 1]
    (`orient`: apply the EXIF orientation of 8-bit PNG and JPEG files)."""
    stored = _read_stored(Path(path), orient)
    return torch.from_numpy(_scaled(stored) if stored.dtype.kind == "u" else stored)


def _scaled(levels: np.ndarray) -> np.ndarray:  # [...] uint8 | uint16 -> [...] float32 in [0, 1]
    return levels.astype(np.float32) / float(np.iinfo(levels.dtype).max)


@functools.lru_cache(maxsize=None)
def _srgb_levels(dtype: str) -> np.ndarray:  # [256] or [65536] float32: each stored level of an integer file, linear
    return srgb_to_linear(torch.from_numpy(_scaled(np.arange(np.iinfo(dtype).max + 1, dtype=dtype)))).numpy()


def _decode_srgb_levels(stored: np.ndarray) -> np.ndarray:  # [H, W, C] uint8 | uint16 -> [H, W, C] float32
    """The colour channels decoded from sRGB by a table of the file depth's levels (`srgb_to_linear` of the scaled
    levels: a gather a value instead of a power), an alpha channel scaled as it is."""
    colour = 3 if stored.shape[-1] >= 3 else 1
    out = np.empty(stored.shape, np.float32)
    np.take(_srgb_levels(stored.dtype.name), stored[..., :colour], out=out[..., :colour])
    out[..., colour:] = _scaled(stored[..., colour:])
    return out


def _read_stored(path: Path, orient: bool) -> np.ndarray:
    """[H, W, C] as the file stores it: uint8 or uint16 for 8- and 16-bit PNG and JPEG (their rarer modes as float32
    in [0, 1]), float32 for the others."""
    if not path.exists():
        raise file_error(path, "file does not exist")
    suffix = path.suffix.lower()
    try:
        if suffix == ".png":
            array = _read_png(path, orient)
        elif suffix in (".jpg", ".jpeg"):
            array = _read_pillow(path, orient)
        elif suffix == ".exr":
            array = _read_exr(path)
        elif suffix == ".hdr":
            array = _read_hdr(path)
        elif suffix == ".npy":
            array = np.load(path).astype(np.float32)
            if array.ndim == 3 and array.shape[0] in (1, 3, 4) and array.shape[-1] not in (1, 3, 4):
                array = np.moveaxis(array, 0, -1)  # CHW -> HWC
        else:
            raise file_error(path, f"unsupported image type '{suffix}'", "use PNG, JPG, EXR or HDR")
    except (TooLarge, Image.DecompressionBombError) as exc:
        raise too_large_error(path, exc) from None
    except MemoryError:
        raise file_error(path, "cannot read image: not enough memory to hold it", "shrink it") from None
    except DECODER_ERRORS as exc:
        raise file_error(path, f"cannot read image: {exc or type(exc).__name__}") from None
    if array.ndim == 2:
        array = array[..., None]
    if array.ndim != 3:
        raise file_error(path, f"expected a 2D image, got an array of shape {array.shape}")
    if array.dtype.kind == "u":
        return np.ascontiguousarray(array)
    if not np.isfinite(array).all():
        bad = int((~np.isfinite(array)).sum())
        raise file_error(path, f"holds {bad} NaN or Inf values", "re-export the file with finite values")
    return np.ascontiguousarray(array, dtype=np.float32)


EXIF_ORIENTATION = 0x0112
EXIF_TRANSPOSED = (5, 6, 7, 8)  # orientations that swap width and height


def image_size(path, orient: bool = False) -> tuple[int, int]:
    """(width, height) of an image file, read from its header where possible (`orient`: as the
    EXIF orientation turns it)."""
    path = Path(path)
    if not path.exists():
        raise file_error(path, "file does not exist")
    if path.suffix.lower() in LDR_SUFFIXES:
        try:
            with Image.open(path) as img:
                width, height = img.size
                if orient and img.getexif().get(EXIF_ORIENTATION) in EXIF_TRANSPOSED:
                    width, height = height, width
            return width, height
        except Image.DecompressionBombError as exc:
            raise too_large_error(path, exc) from None
        except DECODER_ERRORS as exc:
            raise file_error(path, f"cannot read image: {exc or type(exc).__name__}") from None
    values = read_raw(path)
    return int(values.shape[1]), int(values.shape[0])


EXIF_IFD = 0x8769  # the sub-directory of the camera's settings
EXIF_FLASH = 0x9209  # bit 0: the flash fired


def flash_fired(path) -> bool:
    """Whether the photo at `path` was taken with its flash firing, as its EXIF says; False for a file without EXIF
    (PNG renders, EXR) or one that cannot be read (the image's own reading says what is wrong with it)."""
    path = Path(path) if path is not None else None
    if path is None or path.suffix.lower() not in LDR_SUFFIXES or not path.is_file():
        return False
    try:
        with Image.open(path) as img:
            value = img.getexif().get_ifd(EXIF_IFD).get(EXIF_FLASH)
    except (*DECODER_ERRORS, Image.DecompressionBombError, struct.error, ValueError):
        return False
    return isinstance(value, int) and bool(value & 1)


def _read_pillow(path: Path, orient: bool = False) -> np.ndarray:
    with Image.open(path) as img:
        if orient:
            img = ImageOps.exif_transpose(img)
        if img.mode in ("P", "CMYK", "YCbCr", "LAB", "HSV"):
            img = img.convert("RGBA" if "transparency" in img.info else "RGB")
        if img.mode in ("I;16", "I;16B", "I;16L", "I"):
            return np.asarray(img, dtype=np.float32) / 65535.0
        if img.mode == "1":
            img = img.convert("L")
        if img.mode in ("L", "LA", "RGB", "RGBA"):
            return np.asarray(img, dtype=np.uint8)
        return np.asarray(img, dtype=np.float32) / 255.0


def _read_png(path: Path, orient: bool = False) -> np.ndarray:
    try:
        return _read_png_unchecked(path, png, orient)
    except png.Error as exc:  # FormatError, ChunkError, ...
        raise ValueError(str(exc)) from None


def _read_png_unchecked(path: Path, png, orient: bool) -> np.ndarray:
    with open(path, "rb") as handle:
        header = handle.read(33)
    if header[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError("not a PNG file")
    if header[12:16] != b"IHDR":  # the sizes below are IHDR's: a file without it is damaged, not large
        raise ValueError("damaged PNG file: its first chunk is not IHDR")
    bit_depth = header[24]
    if bit_depth != 16:
        return _read_pillow(path, orient)
    check_pixels(int.from_bytes(header[16:20], "big"), int.from_bytes(header[20:24], "big"))  # IHDR's width, height
    width, height, rows, info = png.Reader(filename=str(path)).asDirect()
    planes = info["planes"]
    array = np.vstack([np.asarray(row, dtype=np.uint16) for row in rows]).reshape(height, width, planes)
    return array


def _read_exr(path: Path) -> np.ndarray:
    with OpenEXR.File(str(path), header_only=True) as exr:  # the size first: the pixels are allocated as it says
        (left, top), (right, bottom) = exr.header()["dataWindow"]
    check_pixels(int(right) - int(left) + 1, int(bottom) - int(top) + 1)
    with OpenEXR.File(str(path), separate_channels=True) as exr:
        channels = {name: np.asarray(ch.pixels, dtype=np.float32) for name, ch in exr.channels().items()}
    if not channels:
        raise ValueError("no channels")
    for names in (("R", "G", "B", "A"), ("R", "G", "B"), ("X", "Y", "Z"), ("Y",), ("Z",)):
        if all(n in channels for n in names):
            return np.stack([channels[n] for n in names], axis=-1)
    if len(channels) == 1:
        return next(iter(channels.values()))
    raise ValueError(f"channels {sorted(channels)} are not RGB(A), XYZ, Y or Z")


_HDR_SIZE = re.compile(rb"^([-+])Y (\d+) ([-+])X (\d+)$")


def _read_hdr(path: Path) -> np.ndarray:
    """Radiance RGBE, flat or new-style run-length encoded scanlines."""
    data = path.read_bytes()
    if not (data.startswith(b"#?RADIANCE") or data.startswith(b"#?RGBE")):
        raise ValueError("missing '#?RADIANCE' header")
    end = data.find(b"\n\n")
    if end < 0:
        raise ValueError("header has no blank line")
    size_end = data.find(b"\n", end + 2)
    match = _HDR_SIZE.match(data[end + 2 : size_end])
    if match is None or match.group(1) != b"-" or match.group(3) != b"+":
        raise ValueError("only '-Y H +X W' orientation is supported")
    height, width = int(match.group(2)), int(match.group(4))
    check_pixels(width, height)
    buf = np.frombuffer(data, dtype=np.uint8, offset=size_end + 1)
    if height < 1 or width < 1 or height * width > 16 * len(buf):  # RLE stores at most 127 pixels in 8 bytes
        raise ValueError(f"the header says {width}x{height} pixels but {len(buf)} bytes of pixel data follow")
    rgbe = np.empty((height, width, 4), dtype=np.uint8)
    pos = 0
    for row in range(height):
        if 8 <= width < 0x8000 and buf[pos] == 2 and buf[pos + 1] == 2 and (buf[pos + 2] << 8 | buf[pos + 3]) == width:
            pos += 4
            for channel in range(4):
                col = 0
                while col < width:
                    count = int(buf[pos])
                    if count > 128:  # a run of one value
                        count -= 128
                        rgbe[row, col : col + count, channel] = buf[pos + 1]
                        pos += 2
                    else:  # literal values
                        rgbe[row, col : col + count, channel] = buf[pos + 1 : pos + 1 + count]
                        pos += 1 + count
                    col += count
        else:
            rgbe[row] = buf[pos : pos + 4 * width].reshape(width, 4)
            pos += 4 * width
    exponent = rgbe[..., 3].astype(np.int32)
    scale = np.where(exponent > 0, np.ldexp(1.0, exponent - 136), 0.0).astype(np.float32)
    return (rgbe[..., :3].astype(np.float32) + 0.5 * (exponent[..., None] > 0)) * scale[..., None]


# ------------------------------------------------------------------------------------------ writing
def write_image(path, rgb: Tensor, alpha: Tensor | None = None, bits: int = 8, png_level: int = PNG_LEVEL) -> None:
    """Write linear rgb [H, W, 3] (and alpha [H, W]): sRGB-encoded PNG/JPG, or linear EXR/HDR."""
    path = Path(path)
    values = rgb if path.suffix.lower() in HDR_SUFFIXES else linear_to_srgb(rgb)
    if alpha is not None:
        values = torch.cat([values, alpha[..., None].to(values)], dim=-1)
    write_raw(path, values, bits=bits, png_level=png_level)


def write_raw(path, values: Tensor, bits: int = 8, png_level: int = PNG_LEVEL) -> None:
    """Write stored values [H, W, C] or [H, W] as they are (LDR files clamp to [0, 1]); atomic. `png_level`: zlib's
    compression level of a PNG (SCRATCH_PNG_LEVEL for files only this tool reads back)."""
    path = Path(path)
    array = values.detach().float().cpu().numpy()
    if array.ndim == 3 and array.shape[-1] == 1:
        array = array[..., 0]
    suffix = path.suffix.lower()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = atomic_target(path)
    if suffix == ".png":
        _write_png(tmp, array, bits, png_level)
    elif suffix in (".jpg", ".jpeg"):
        Image.fromarray(np.round(np.clip(array, 0, 1) * 255).astype(np.uint8)).save(tmp, quality=95)
    elif suffix == ".exr":
        _write_exr(tmp, array)
    elif suffix == ".hdr":
        _write_hdr(tmp, array)
    else:
        raise file_error(path, f"unsupported image type '{suffix}'", "use PNG, JPG, EXR or HDR")
    _publish(tmp, path)


def _write_png(path: Path, array: np.ndarray, bits: int, level: int) -> None:
    if bits not in (8, 16):
        raise ValueError(f"PNG bit depth must be 8 or 16, got {bits}")
    if bits == 8:
        Image.fromarray(np.round(np.clip(array, 0, 1) * 255).astype(np.uint8)).save(path, compress_level=level)
        return
    ints = np.round(np.clip(array, 0, 1) * 65535).astype(np.uint16)
    height, width = ints.shape[:2]
    planes = 1 if ints.ndim == 2 else ints.shape[2]
    greyscale, has_alpha = planes in (1, 2), planes in (2, 4)
    writer = png.Writer(width, height, greyscale=greyscale, alpha=has_alpha, bitdepth=16, compression=level)
    with open(path, "wb") as handle:
        writer.write(handle, ints.reshape(height, width * planes))


def _write_exr(path: Path, array: np.ndarray) -> None:
    array = np.ascontiguousarray(array, dtype=np.float32)
    if array.ndim == 2:
        channels = {"Y": array}
    else:
        names = {1: "Y", 3: "RGB", 4: "RGBA"}.get(array.shape[-1])
        if names is None:
            raise ValueError(f"EXR needs 1, 3 or 4 channels, got {array.shape[-1]}")
        channels = {names: array} if array.shape[-1] > 1 else {"Y": array[..., 0]}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, channels) as exr:
        exr.write(str(path))


def _write_hdr(path: Path, array: np.ndarray) -> None:
    if array.ndim == 2:
        array = np.repeat(array[..., None], 3, axis=-1)
    rgb = np.clip(array[..., :3].astype(np.float64), 0.0, None)
    brightest = rgb.max(axis=-1)
    mantissa, exponent = np.frexp(brightest)
    scale = np.where(brightest > 1e-32, mantissa * 256.0 / np.maximum(brightest, 1e-32), 0.0)
    rgbe = np.zeros(rgb.shape[:2] + (4,), dtype=np.uint8)
    rgbe[..., :3] = np.clip(np.floor(rgb * scale[..., None]), 0, 255).astype(np.uint8)
    rgbe[..., 3] = np.where(brightest > 1e-32, exponent + 128, 0).astype(np.uint8)
    height, width = rgb.shape[:2]
    with open(path, "wb") as handle:
        handle.write(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n" + f"-Y {height} +X {width}\n".encode())
        handle.write(rgbe.tobytes())


# ------------------------------------------------------------------------------------------ resampling
def resize(image: Tensor, height: int, width: int, mode: str = "area") -> Tensor:
    """Resample an image [H, W, C] or [H, W] to [height, width(, C)].

    `mode`: 'area' (antialiased bilinear, for photos and continuous maps), 'box' (each output pixel the mean of the
    pixels it covers when shrinking, bilinear when enlarging: a step between whole pixels stays a step) or 'nearest'
    (masks, ids).
    """
    squeeze = image.ndim == 2
    x = image[..., None] if squeeze else image
    if tuple(x.shape[:2]) == (height, width):
        return image
    x = x.permute(2, 0, 1)[None].float()
    if mode == "nearest":
        out = F.interpolate(x, size=(height, width), mode="nearest")
    elif mode == "area":
        out = F.interpolate(x, size=(height, width), mode="bilinear", align_corners=False, antialias=True)
    elif mode == "box":
        shrinks = height <= x.shape[2] and width <= x.shape[3]
        out = F.interpolate(x, size=(height, width), mode="area" if shrinks else "bilinear")
    else:
        raise ValueError(f"unknown resize mode '{mode}'")
    out = out[0].permute(1, 2, 0)
    return out[..., 0] if squeeze else out
