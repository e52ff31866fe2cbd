"""Mitsuba and Dr.Jit cut down to what `matspray synth` renders the paper preset's object with, as one archive small
enough to carry to a machine without a package registry (the GPU machine: a 64 MiB carry limit).

    python -m benchmarks.mitsuba_reduced --out .gpu-data/mitsuba.tar.xz [--variants cuda_ad_rgb scalar_rgb]
                                         [--wheels drjit-*.whl mitsuba-*.whl]

Kept: Dr.Jit without its C++ headers; Mitsuba's Python files and shared libraries, the variants named (on the GPU
machine `cuda_ad_rgb`, which needs only the NVIDIA driver, and `scalar_rgb` as the fallback; `llvm_ad_rgb` needs an
LLVM there) and only the plugins that `synth` loads for the demo object (found by rendering a tiny one, with the
paper's sampler, and the scene `select_variant` checks a variant with, with `scalar_rgb` in a subprocess, and reading
which plugin libraries it mapped; a plugin is one library for every variant). Left out:
the other variants, the other plugins, headers, type stubs, Mitsuba's spectral data.

On the other machine: `mkdir -p M && tar -xJf mitsuba.tar.xz -C M && export PYTHONPATH=$PWD/M:$PYTHONPATH`, then
`matspray synth` and `matspray demo --preset paper` find it (benchmarks/gpu_check.sh does this).
"""

from __future__ import annotations

import argparse
import io
import json
import subprocess
import sys
import tarfile
import zipfile
from functools import partial
from pathlib import Path
from typing import Callable

# which plugin libraries a render maps, in a subprocess of its own (so nothing loaded before counts)
PROBE = """
import json, math, sys
from matspray.presets import DEMO_SIZES
from matspray.synth import mitsuba_scene
exec(mitsuba_scene._PROBE.format(variant="scalar_rgb"))  # the scene `select_variant` checks a variant with
mitsuba_scene.VARIANTS, mitsuba_scene.GPU_VARIANT = ("scalar_rgb",), "scalar_rgb"
from matspray.synth.config import SynthConfig
from matspray.synth.make import make_object
spp = 4 if math.isqrt(DEMO_SIZES["paper"].spp) ** 2 == DEMO_SIZES["paper"].spp else 2  # the paper's sampler
config = SynthConfig(shape=sys.argv[2], seed=int(sys.argv[3]), resolution=12, train_views=1, test_views=1, spp=spp)
make_object(config, sys.argv[1], progress=False, notify=lambda s: None)
import mitsuba
mapped = {line.split()[-1] for line in open("/proc/self/maps") if "/plugins/" in line}
plugins = sorted(p.rsplit("/", 1)[1] for p in mapped if p.endswith(".so"))
print(json.dumps({"plugins": plugins, "mitsuba": mitsuba.__file__}))
"""
SKIPPED_DIRS = ("include", "__pycache__", "data", "plugins")
VARIANT_SUFFIX = ".cpython-"


def probe(work: Path, shape: str = "composite", seed: int = 0, environment: dict | None = None) -> dict:
    """A tiny render of `shape` (the demo object's by default) with scalar_rgb into `work`, in a subprocess (with
    `environment`): {plugins: the plugin libraries it loaded, mitsuba: the package's file it imported}."""
    done = subprocess.run(
        [sys.executable, "-c", PROBE, str(work), shape, str(seed)],
        capture_output=True,
        text=True,
        env=environment,
    )
    if done.returncode != 0:
        raise RuntimeError(f"the probe's render failed: {done.stderr.strip()[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def kept(relative: str, variants: tuple[str, ...], plugins: list[str]) -> bool:
    """Whether `relative` (a path inside site-packages: drjit/..., mitsuba/...) is kept."""
    package, *parts = relative.split("/")
    if package not in ("drjit", "mitsuba") or not parts:
        return False
    if package == "drjit":
        return not any(p in ("include", "__pycache__") for p in parts)
    if parts[0] == "plugins":
        return len(parts) == 2 and parts[1] in plugins
    if any(p in SKIPPED_DIRS for p in parts) or relative.endswith(".pyi"):
        return False
    name = parts[-1]
    stem = name.split(VARIANT_SUFFIX)[0]
    if VARIANT_SUFFIX in name and "_" in stem and not stem.startswith("mitsuba_"):
        return stem in variants  # a variant's module: scalar_rgb.cpython-311-...so
    return True


def installed_files() -> list[tuple[str, Callable[[], bytes]]]:
    """(path inside site-packages, its bytes) of the installed drjit and mitsuba packages."""
    import drjit
    import mitsuba

    files = []
    for module in (drjit, mitsuba):
        root = Path(module.__file__).parent
        for path in sorted(root.rglob("*")):
            if path.is_file():
                files.append((f"{root.name}/{path.relative_to(root)}", path.read_bytes))
    return files


def wheel_files(wheels: list[Path]) -> list[tuple[str, Callable[[], bytes]]]:
    """(path inside site-packages, its bytes) of drjit's and mitsuba's wheels (another Python's: the GPU machine's)."""
    files = []
    for wheel in wheels:
        archive = zipfile.ZipFile(wheel)
        for name in archive.namelist():
            if not name.endswith("/"):
                files.append((name, partial(archive.read, name)))
    return files


def build(out: Path, variants: tuple[str, ...], work: Path, wheels: list[Path] | None = None, level: int = 6) -> dict:
    """Write the archive from the installed packages or from `wheels` (xz at `level`); return what it holds and its
    size. The probe's render of the tiny object is left in `work`."""
    import mitsuba

    plugins = probe(work)["plugins"]
    source = wheel_files(wheels) if wheels else installed_files()
    files, raw = 0, 0
    out.parent.mkdir(parents=True, exist_ok=True)
    with tarfile.open(out, "w:xz", preset=level) as archive:
        for relative, read in source:
            if not kept(relative, variants, plugins):
                continue
            data = read()
            info = tarfile.TarInfo(relative)
            info.size, info.mode = len(data), 0o755
            archive.addfile(info, io.BytesIO(data))
            files, raw = files + 1, raw + len(data)
        made_from = [w.name for w in wheels] if wheels else f"installed mitsuba {mitsuba.__version__}"
        stamp = json.dumps({"from": made_from, "variants": variants, "plugins": plugins}).encode()
        info = tarfile.TarInfo("mitsuba-reduced.json")
        info.size = len(stamp)
        archive.addfile(info, io.BytesIO(stamp))
    return {"files": files, "raw_bytes": raw, "archive_bytes": out.stat().st_size, "plugins": plugins}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path(".gpu-data/mitsuba.tar.xz"))
    parser.add_argument("--variants", nargs="+", default=["cuda_ad_rgb", "scalar_rgb"])
    parser.add_argument("--work", type=Path, default=Path("runs/mitsuba-probe"), help="where the probe renders")
    wheels = "drjit's and mitsuba's wheels to cut down (default: the installed packages; the GPU machine's Python "
    wheels += "needs its own: benchmarks/gpu_wheels.sh)"
    parser.add_argument("--wheels", type=Path, nargs="+", help=wheels)
    args = parser.parse_args()
    figures = build(args.out, tuple(args.variants), args.work, args.wheels)
    print(f"{args.out}: {figures['files']} files, {figures['raw_bytes'] / 2**20:.1f} MiB unpacked, "
          f"{figures['archive_bytes'] / 2**20:.1f} MiB packed; variants {', '.join(args.variants)}; "
          f"plugins {', '.join(p[:-3] for p in figures['plugins'])}")  # fmt: skip


if __name__ == "__main__":
    main()
