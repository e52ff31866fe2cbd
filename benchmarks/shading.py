"""Shading figures: BRDF table accuracy and cost, prefiltering cost, G-buffer shading cost, and the split-sum
error against the numerically integrated reference (with and without the dominant-direction correction).

    python -m benchmarks.shading            (from the repository root; about a minute on 2 CPU cores)
"""

from __future__ import annotations

import time

import torch

from matspray.data.camera import Camera
from matspray.render.shade import brdf_lut, deferred
from matspray.render.shade.brdf import reflect
from matspray.render.shade.deferred import GBuffer, shade, shade_by_quadrature, shade_gbuffer
from matspray.render.shade.envmap import _KERNELS, EnvironmentMap, prefilter_latlong
from matspray.render.shade.latlong import pixel_directions

f64 = torch.float64


def timed(fn, repeats: int = 1) -> float:
    start = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - start) / repeats


def sky_map(height: int, dtype=f64) -> torch.Tensor:
    """Smooth test light: vertical gradient, soft horizon to a warm ground, one broad blob (as in the tests)."""
    d = pixel_directions(height, 2 * height, dtype=dtype)
    z = d[..., 2:]
    sky = torch.tensor([0.3, 0.5, 0.9], dtype=dtype) * (0.6 + 0.4 * z)
    ground = torch.tensor([0.2, 0.15, 0.1], dtype=dtype) * torch.sigmoid(-z / 0.15)
    blob_dir = torch.nn.functional.normalize(torch.tensor([0.5, 0.3, 0.6], dtype=dtype), dim=0)
    blob = torch.exp(((d * blob_dir).sum(-1, keepdim=True) - 1) / 0.08)
    return sky + ground + 4.0 * blob * torch.tensor([1.0, 0.9, 0.7], dtype=dtype)


def lut_figures() -> None:
    brdf_lut._TABLES.clear()
    seconds = timed(lambda: brdf_lut.brdf_lut(brdf_lut.DEFAULT_SIZE, brdf_lut.DEFAULT_SAMPLES))
    centres = (torch.arange(brdf_lut.DEFAULT_SIZE, dtype=f64) + 0.5) / brdf_lut.DEFAULT_SIZE
    nv, r = torch.meshgrid(centres, centres, indexing="ij")
    reference = torch.cat(
        [brdf_lut.integrate_split_sum(nv[i : i + 2], r[i : i + 2], 1 << 16) for i in range(0, len(centres), 2)]
    )
    table = brdf_lut.brdf_lut(dtype=f64)
    error = (table - reference).abs()
    print(
        f"BRDF table {brdf_lut.DEFAULT_SIZE}x{brdf_lut.DEFAULT_SIZE}, {brdf_lut.DEFAULT_SAMPLES} VNDF samples: "
        f"built in {seconds:.3f} s; |A, B - 65k-sample reference| max {error.max():.2e}, mean {error.mean():.2e}"
    )


def prefilter_figures() -> None:
    for height in (32, 64, 128):
        env = EnvironmentMap.from_tensor(sky_map(height).float())
        _KERNELS.clear()
        cold = timed(lambda: env.prefilter())
        warm = timed(lambda: env.prefilter(), repeats=5)

        def step():
            pre = env.prefilter()
            loss = sum(level.sum() for level in pre.specular) + pre.irradiance.sum()
            loss.backward()

        backward = timed(step, repeats=3)
        kernel_mb = sum(k.numel() * k.element_size() for k in _KERNELS.values()) / 2**20
        print(
            f"prefilter {height}x{2 * height} float32, 12 levels + irradiance: first call (kernels) {cold:.3f} s, "
            f"then {warm * 1000:.1f} ms forward, {backward * 1000:.1f} ms forward+backward; kernels {kernel_mb:.1f} MiB"
        )


def gbuffer_figures(size: int = 128) -> None:
    g = torch.Generator().manual_seed(0)
    camera = Camera.look_at(eye=(0.0, -3.0, 1.0), target=(0, 0, 0), up=(0, 0, 1), fov_x=0.6, width=size, height=size)
    maps = {
        "base_color": torch.rand(size, size, 3, generator=g),
        "roughness": torch.rand(size, size, generator=g),
        "metallic": torch.rand(size, size, generator=g),
        "normals": torch.randn(size, size, 3, generator=g),
    }
    for t in maps.values():
        t.requires_grad_(True)
    env = EnvironmentMap.from_tensor(sky_map(64).float())
    env.prefilter()  # kernels

    def step():
        image = shade_gbuffer(GBuffer(alpha=torch.ones(size, size), **maps), camera, env)
        image.mean().backward()

    seconds = timed(step, repeats=3)
    print(
        f"shade_gbuffer {size}x{size} with a 64x128 learnable map (prefilter included): "
        f"{seconds * 1000:.0f} ms forward+backward"
    )


GEOMETRIES = {
    "head-on": ((0, 0, 1), (0.3, 0.1, 1)),
    "oblique": ((0.4, 0.2, 0.8), (0.5, 0.5, 0.3)),
    "horizontal": ((1, 0, 0.1), (0.6, -0.7, 0.2)),
    "downward": ((-0.3, 0.4, -0.8), (0.2, 0.9, -0.3)),
}


def split_sum_figures() -> None:
    light = sky_map(32)
    prefiltered = prefilter_latlong(light)
    base = torch.tensor([0.8, 0.6, 0.4], dtype=f64)
    metallic = torch.tensor([0.0, 0.5, 1.0], dtype=f64)
    dominant = deferred.specular_direction
    print("split-sum vs quadrature reference, 32x64 sky map, base color (0.8, 0.6, 0.4): max relative error over RGB")
    print(f"{'geometry':>11} {'r':>4}  {'m=0':>6} {'m=0.5':>6} {'m=1':>6}   without dominant direction: m=0.5, m=1")
    for name, (n, wo) in GEOMETRIES.items():
        n, wo = (torch.nn.functional.normalize(torch.tensor(v, dtype=f64), dim=0).expand(3, 3) for v in (n, wo))
        for roughness in (0.2, 0.5, 0.9):
            r = torch.full((3,), roughness, dtype=f64)
            reference = shade_by_quadrature(
                base.expand(3, 3), r, metallic, n, wo, light, rows=256 if roughness < 0.5 else 128
            )
            errors = []
            for direction in (dominant, lambda n, wo, r: reflect(-wo, n)):
                deferred.specular_direction = direction
                got = shade(base.expand(3, 3), r, metallic, n, wo, prefiltered)
                errors.append(((got - reference) / reference).abs().amax(-1).tolist())
            deferred.specular_direction = dominant
            with_d, without_d = errors
            print(
                f"{name:>11} {roughness:4.1f}  "
                + " ".join(f"{e:6.3f}" for e in with_d)
                + "   "
                + " ".join(f"{e:6.3f}" for e in without_d[1:])
            )


if __name__ == "__main__":
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    lut_figures()
    prefilter_figures()
    gbuffer_figures()
    split_sum_figures()
