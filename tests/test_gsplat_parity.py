"""gsplat's own rasterization() run on the CPU (tests/gsplat_cpu.py) against backend torch: images, alpha, depths,
means2d, radii, every gradient, absgrad, densification statistics, and each setting the two could differ in. Where
CUDA and gsplat are present, the same comparison runs on gsplat's real kernels. How the backend is chosen is
tests/test_gsplat_backend.py."""

from __future__ import annotations

import math
import re
from pathlib import Path

import gsplat
import pytest
import torch

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians
from matspray.geometry.config import GeometryConfig
from matspray.geometry.densify import DensityControl
from matspray.render import backend as backend_module
from matspray.render.backend import gsplat_import_error
from matspray.render.raster.rasterize import rasterize
from matspray.render.settings import RasterSettings
from tests import gsplat_cpu
from tests.gsplat_cpu import gsplat_on_cpu
from tests.test_rasterize import random_scene

OPAQUE_LOGIT = 20.0  # sigmoid(20) rounds to exactly 1 in float32


@pytest.fixture(autouse=True)
def fresh_backend_checks(monkeypatch):
    """Each test starts with nothing checked or told yet in this process."""
    monkeypatch.setattr(backend_module, "_CHECKED", {})
    monkeypatch.setattr(backend_module, "_TOLD", set())


# ---------------------------------------------------------------- the harness is gsplat's kernels


def kernel_constant(source: str, pattern: str) -> float:
    match = re.search(pattern, source)
    assert match, pattern
    return float(match.group(1))


def test_harness_constants_are_those_of_the_installed_kernels():
    """The harness reads as the installed gsplat's CUDA source does (a gsplat upgrade that changes it fails here)."""
    cuda = Path(gsplat.__file__).parent / "cuda"
    blend = (cuda / "csrc" / "RasterizeToPixels3DGSFwd.cu").read_text()
    number = r"([0-9.]+(?:e-?[0-9]+)?)f"
    assert kernel_constant(blend, rf"float alpha = min\({number}, opac \* __expf\(-sigma\)\);") == gsplat_cpu.MAX_ALPHA
    assert (
        kernel_constant(blend, rf"if \(next_T <= {number}\) {{ // this pixel is done: exclusive")
        == gsplat_cpu.DONE_TRANSMITTANCE
    )
    assert "if (sigma < 0.f || alpha < ALPHA_THRESHOLD) {\n                continue;" in blend
    assert "float px = (float)j + 0.5f;" in blend and "float py = (float)i + 0.5f;" in blend
    common = (cuda / "include" / "Common.h").read_text()
    assert 1.0 / kernel_constant(common, rf"#define ALPHA_THRESHOLD \(1.f / {number}\)") == gsplat_cpu.ALPHA_THRESHOLD
    projection = (cuda / "csrc" / "ProjectionEWA3DGSFused.cu").read_text()
    assert kernel_constant(projection, rf"float extend = {number};") == gsplat_cpu.MAX_EXTEND
    assert "extend = min(extend, sqrt(2.0f * __logf(opacity / ALPHA_THRESHOLD)));" in projection
    assert "if (mean_c.z < near_plane || mean_c.z > far_plane) {" in projection


def test_harness_radii_without_opacities_are_gsplats_reference():
    """Without opacities the kernel's radii are 3.33 sigma per axis, what gsplat's torch reference returns."""
    gaussians, camera, _ = random_scene(30, 4, width=40, height=36)
    g = gaussians.detach()
    args = (g.means, None, g.quats, g.scales, camera.viewmat[None], camera.K[None], 40, 36)
    radii = gsplat_cpu.fully_fused_projection(*args)[0]
    covars, _ = gsplat_cpu._quat_scale_to_covar_preci(g.quats, g.scales, compute_preci=False)
    reference = gsplat_cpu._fully_fused_projection(g.means, covars, camera.viewmat[None], camera.K[None], 40, 36)[0]
    assert (radii > 0).any() and torch.equal(radii, reference)


# ---------------------------------------------------------------- gsplat (on the CPU) against torch


def leaves(gaussians: Gaussians, features):
    g = Gaussians(
        *(
            t.detach().clone().requires_grad_(True)
            for t in (gaussians.means, gaussians.log_scales, gaussians.quats, gaussians.opacity_logits)
        ),
        gaussians.sh,
    )
    return g, features.detach().clone().requires_grad_(True)


def loss_of(features, alpha, depth):  # a loss on every output: weighted features, alpha squared, depth
    weights = torch.linspace(0.5, 1.5, features.shape[-1], dtype=features.dtype)
    return torch.sum(features * weights) + alpha.square().sum() + 0.1 * depth.sum()


def render_and_backward(backend, gaussians, camera, features, background=None, absgrad=True, settings=RasterSettings()):
    """rasterize and backward of `loss_of`: (out, leaf Gaussians, leaf features), with their gradients."""
    g, f = leaves(gaussians, features)
    out = rasterize(g, camera, f, background, backend=backend, absgrad=absgrad, settings=settings)
    out.retain_screen_grads()
    loss_of(out.features, out.alpha, out.depth).backward()
    return out, g, f


def assert_matches(actual, expected, rel=1e-5, scale=None):
    """Equal to float32 rounding: every element within rel times `scale`, by default the largest |expected|.
    Both backends run in float32 and sum in other orders; gradients through the transmittance behind a nearly
    opaque hit (1 - alpha = 1e-3) lose most: measured up to 4.9e-6 (test_eps2d_zero...), 1.3e-6 in the random
    scenes. In float64 the two agree to 1e-13 (test_gsplat_rules_are_ours_in_float64)."""
    scale = float(expected.detach().abs().max()) if scale is None else float(scale)
    torch.testing.assert_close(actual, expected, rtol=0, atol=rel * scale + 1e-30)


def parity_scene(seed: int, n: int = 40, width: int = 40, height: int = 36):
    """A random scene over 3 x 3 tiles of 16 px, opacities up to 1, four of them exactly 1, two Gaussians behind the
    camera."""
    gaussians, camera, features = random_scene(n, seed, width=width, height=height, max_opacity=1.0)
    logits = gaussians.opacity_logits.clone()
    logits[:4] = OPAQUE_LOGIT
    means = gaussians.means.clone()
    means[-2:] = 2.0 * camera.center.float() - means[-2:]  # mirrored through the camera centre: behind it
    return Gaussians(means, gaussians.log_scales, gaussians.quats, logits, gaussians.sh), camera, features


def assert_same_rendering(a, b):
    """Everything two render_and_backward runs return agrees to float32 rounding."""
    (ta, ga, fa), (tb, gb, fb) = a, b
    for name in ("features", "alpha", "depth"):
        assert_matches(getattr(tb, name), getattr(ta, name))
    # expected depth = depth / alpha: gsplat's alpha is 1 - T in float32, whose rounding (6e-8) the division
    # scales by 1 / alpha where alpha is small
    expected = ta.expected_depth
    slack = 1e-6 * expected / ta.alpha.clamp_min(1e-12) + 2e-5
    assert ((tb.expected_depth - expected).abs() <= slack).all()
    assert torch.equal(tb.visible, ta.visible)
    assert_matches(tb.radii, ta.radii)
    assert_matches(tb.means2d[ta.visible], ta.means2d[ta.visible])
    if ta.screen_absgrads is None:  # rendered without absgrad
        assert tb.screen_absgrads is None
        assert_matches(tb.screen_grads, ta.screen_grads)
    else:  # a sum of per-pixel terms that may cancel (a symmetric scene): rounding scales with the terms,
        # |sum| <= absgrad
        assert_matches(tb.screen_absgrads, ta.screen_absgrads)
        assert_matches(tb.screen_grads, ta.screen_grads, scale=ta.screen_absgrads.max())
    for name in ("means", "log_scales", "quats", "opacity_logits"):
        assert_matches(getattr(gb, name).grad, getattr(ga, name).grad)
    assert_matches(fb.grad, fa.grad)


@pytest.mark.parametrize("seed", [0, 1])
def test_gsplat_rules_are_ours_in_float64(monkeypatch, seed):
    """gsplat.rasterization on the CPU in float64 (backend gsplat casts to float32, as gsplat's CUDA kernels
    need) against backend torch in float64: the same blending rules, so equal to 1e-10."""
    gsplat_on_cpu(monkeypatch)
    gaussians, camera, features = parity_scene(seed)
    a, ga, fa = render_and_backward("torch", gaussians.to(dtype=torch.float64), camera, features.double())
    gb, fb = leaves(gaussians.to(dtype=torch.float64), features.double())
    colors, alphas, meta = gsplat.rasterization(
        gb.means,
        gb.quats,
        gb.scales,
        gb.opacities,
        fb,
        camera.viewmat[None].double(),
        camera.K[None].double(),
        camera.width,
        camera.height,
        packed=False,
        render_mode="RGB+D",
        absgrad=True,
    )
    screen = meta["means2d"]
    screen.retain_grad()
    loss_of(colors[0, ..., :-1], alphas[0, ..., 0], colors[0, ..., -1]).backward()
    for actual, expected in (
        (colors[0, ..., :-1], a.features),
        (alphas[0, ..., 0], a.alpha),
        (colors[0, ..., -1], a.depth),
        (screen[0][a.visible], a.screen[a.visible]),
        (screen.grad[0], a.screen_grads),
        (screen.absgrad[0], a.screen_absgrads),
        (fb.grad, fa.grad),
        *((getattr(gb, k).grad, getattr(ga, k).grad) for k in ("means", "log_scales", "quats", "opacity_logits")),
    ):
        assert_matches(actual, expected, rel=1e-10)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_gsplat_matches_torch(monkeypatch, seed):
    gsplat_on_cpu(monkeypatch)
    gaussians, camera, features = parity_scene(seed)
    background = torch.tensor([0.2, 0.5, 0.9])
    torch_run = render_and_backward("torch", gaussians, camera, features, background)
    gsplat_run = render_and_backward("gsplat", gaussians, camera, features, background)
    a, b = torch_run[0], gsplat_run[0]
    assert a.backend == "torch" and b.backend == "gsplat"
    assert a.alpha.max() > 0.99 and (a.alpha < 0.5).any()  # opaque and open pixels
    assert not a.visible[-2:].any()  # behind the camera
    assert b.tile_hits > int(b.visible.sum()) and a.pixel_hits > 0  # some Gaussians span more than one tile
    assert_same_rendering(torch_run, gsplat_run)


@pytest.mark.parametrize("absgrad", [False, True])
def test_gsplat_with_more_channels_than_a_chunk(monkeypatch, absgrad):
    """gsplat renders more than 32 channels in chunks, and each chunk's backward replaces means2d.absgrad with its
    own: backend gsplat renders them in one chunk when absgrad is asked for (in chunks otherwise)."""
    gsplat_on_cpu(monkeypatch)
    gaussians, camera, _ = parity_scene(5, n=24, width=24, height=20)
    features = torch.rand(24, 40, generator=torch.Generator().manual_seed(0))
    assert_same_rendering(
        render_and_backward("torch", gaussians, camera, features, absgrad=absgrad),
        render_and_backward("gsplat", gaussians, camera, features, absgrad=absgrad),
    )


@pytest.mark.parametrize("absgrad", [False, True])
def test_densification_statistics_match(monkeypatch, absgrad):
    gsplat_on_cpu(monkeypatch)
    gaussians, camera, features = parity_scene(6)
    controls = []
    for backend in ("torch", "gsplat"):
        control = DensityControl(GeometryConfig(absgrad=absgrad), extent=1.0, num_gaussians=len(gaussians))
        for view in range(2):  # two observations of the same view: the statistics add up
            out, _, _ = render_and_backward(backend, gaussians, camera, features, absgrad=absgrad)
            control.observe(out, camera.width, camera.height)
        controls.append(control)
    a, b = controls
    assert a.count.max() == 2 and (a.count == 0).any()
    assert torch.equal(b.count, a.count)
    assert_matches(b.grad_sum, a.grad_sum)
    assert_matches(b.max_radius, a.max_radius)


# ---------------------------------------------------------------- settings: equal, or the differences documented


def axis_camera(size: int, fov_degrees: float = 60.0, cx: float | None = None) -> Camera:
    """A camera at the origin looking down +z (world = camera coordinates), `size` x `size` pixels."""
    camera = Camera.from_fov_x(math.radians(fov_degrees), size, size, torch.eye(4))
    if cx is not None:
        camera.K[0, 2] = cx
    return camera


def gaussians_at(centres, scales, opacity_logits) -> Gaussians:
    n = len(centres)
    return Gaussians(
        torch.tensor(centres, dtype=torch.float32),
        torch.log(torch.tensor(scales, dtype=torch.float32)),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        torch.tensor(opacity_logits, dtype=torch.float32),
        torch.zeros(n, 1, 3),
    )


def test_opaque_stack_blends_and_stops_alike(monkeypatch):
    """Opacity exactly 1, then 0.97 and 1 again, stacked on the axis: the same images and gradients. At the centre
    pixel the first alpha is clamped to max_alpha and the pixel stops before the second (T would be 3e-5);
    around it, where the first is fainter, the ones behind show."""
    gsplat_on_cpu(monkeypatch)
    n = 5
    centres = [[0.0, 0.0, 2.0 + 0.2 * k] for k in range(n)]
    gaussians = gaussians_at(
        centres, [[0.3, 0.3, 0.3]] * n, [OPAQUE_LOGIT, math.log(0.97 / 0.03), OPAQUE_LOGIT, 0.0, 0.0]
    )
    features, background = torch.eye(n), torch.full((n,), 0.5)
    runs = [
        render_and_backward(backend, gaussians, axis_camera(9), features, background) for backend in ("torch", "gsplat")
    ]
    assert_same_rendering(*runs)
    max_alpha = RasterSettings().max_alpha
    only_the_first = torch.tensor([max_alpha] + [0.0] * (n - 1)) + (1.0 - max_alpha) * background
    for out, _, _ in runs:
        torch.testing.assert_close(out.features[4, 4], only_the_first)
        assert (out.features[..., 1:3] > 0.5 * (1.0 - out.alpha[..., None])).any()  # the ones behind, off the centre


def test_transmittance_stop_differs_only_at_1e_4_within_rounding(monkeypatch):
    """Two Gaussians on one pixel centre each, the second leaving T near 1e-4: gsplat blends it while
    T(1 - alpha) > 1e-4 in float32, we while it is >= 1e-4 in float64 logs; they agree wherever T(1 - alpha)
    is more than float32 rounding away from 1e-4."""
    gsplat_on_cpu(monkeypatch)
    pairs, spacing = 64, 4  # pixels 4 apart: neighbours' alphas there are below 1/255
    side = 8 * spacing + 1
    camera = axis_camera(side, fov_degrees=90.0)
    focal = float(camera.K[0, 0])
    first = 0.92 + 0.07 * torch.rand(pairs, generator=torch.Generator().manual_seed(1))  # the second stays below 0.999
    second = 1.0 - 1e-4 / (1.0 - first) * (1.0 + 4e-4 * torch.linspace(-1, 1, pairs))  # T after it: 1e-4 (1 +- 4e-4)
    pixels = [((k % 8) * spacing + 2.5 - side / 2, (k // 8) * spacing + 2.5 - side / 2) for k in range(pairs)]
    centres = [[x * z / focal, y * z / focal, z] for z in (2.0, 2.5) for x, y in pixels]  # on pixel centres
    logits = torch.logit(torch.cat([first, second]).double()).tolist()
    gaussians = gaussians_at(centres, [[1e-3] * 3] * (2 * pairs), logits)
    features = torch.cat([torch.zeros(pairs, 1), torch.ones(pairs, 1)])  # channel 0: the second Gaussian's weight
    opacity = gaussians.opacities.double()
    after = (1.0 - opacity[:pairs]) * (1.0 - opacity[pairs:])  # [pairs] T after the second, float64
    off = (after / 1e-4 - 1.0).abs()
    clear = off > 3e-6  # our float32 log1p terms: up to about 1e-6 relative in T; gsplat's float32 product 1.2e-7
    assert (clear & (off < 2e-5)).sum() >= 4 and (after < 1e-4).any() and (after > 1e-4).any()  # close, on both sides
    cols, rows = (torch.tensor([int(c + side / 2) for c in axis]) for axis in zip(*pixels))
    blended = [
        rasterize(gaussians, camera, features, backend=backend).features[rows, cols, 0] > 0
        for backend in ("torch", "gsplat")
    ]
    assert torch.equal(blended[0][clear], blended[1][clear])
    assert torch.equal(blended[0][clear], (after >= 1e-4)[clear])


def test_near_plane_gsplat_draws_a_centre_exactly_on_it(monkeypatch):
    gsplat_on_cpu(monkeypatch)
    near = RasterSettings().near
    camera, features = axis_camera(9), torch.ones(1, 1)
    on_plane = gaussians_at([[0.0, 0.0, near]], [[1e-3] * 3], [OPAQUE_LOGIT])
    a, b = (rasterize(on_plane, camera, features, backend=backend) for backend in ("torch", "gsplat"))
    assert not a.visible[0] and a.alpha.max() == 0
    assert b.visible[0] and b.alpha.max() > 0.99
    beyond = gaussians_at([[0.0, 0.0, near * 1.01]], [[1e-3] * 3], [OPAQUE_LOGIT])
    assert_same_rendering(*(render_and_backward(backend, beyond, camera, features) for backend in ("torch", "gsplat")))


def test_eps2d_zero_alike_and_singular_footprints_culled_by_both(monkeypatch):
    """Without the low-pass filter: the same images and gradients, and a Gaussian flat along camera y seen
    edge-on (2D covariance diag(., 0), exactly singular) culled by both (gsplat: det <= 0, ours det <= 1e-12
    relative; they differ only for footprints singular to within rounding)."""
    gsplat_on_cpu(monkeypatch)
    settings = RasterSettings(eps2d=0.0)
    gaussians, camera, features = parity_scene(7)
    assert_same_rendering(
        *(
            render_and_backward(backend, gaussians, camera, features, settings=settings)
            for backend in ("torch", "gsplat")
        )
    )
    flat_edge_on = gaussians_at(
        [[0.0, 0.0, 2.0], [0.05, 0.02, 2.2]], [[0.1, 0.0, 0.1], [0.1, 0.05, 0.1]], [OPAQUE_LOGIT] * 2
    )
    runs = [
        render_and_backward(backend, flat_edge_on, axis_camera(9), torch.eye(2), settings=settings)
        for backend in ("torch", "gsplat")
    ]
    assert_same_rendering(*runs)
    assert runs[0][0].visible.tolist() == [False, True]


def test_jacobian_clamp_differs_only_off_centre_and_beyond_it(monkeypatch):
    """The projection Jacobian's direction clamp: ours 1.3 cx / fx, gsplat's cx / fx + 0.15 W / fx, equal for a
    centred principal point. With cx = W / 4, a large Gaussian centred at x / z = -0.5 W / fx (beyond both
    clamps, left of the image) reaches into it with other footprints; one at -0.2 W / fx (inside both) agrees."""
    gsplat_on_cpu(monkeypatch)
    size = 24
    for cx, x_over_width, same in ((size / 4, -0.2, True), (size / 4, -0.5, False), (size / 2, -0.7, True)):
        camera = axis_camera(size, cx=cx)
        z = 2.0
        gaussians = gaussians_at(
            [[x_over_width * size / float(camera.K[0, 0]) * z, 0.0, z]], [[0.4, 0.25, 0.3]], [OPAQUE_LOGIT]
        )
        a, b = (render_and_backward(backend, gaussians, camera, torch.ones(1, 1)) for backend in ("torch", "gsplat"))
        assert a[0].alpha.max() > 0.05
        if same:
            assert_same_rendering(a, b)
        else:
            assert (a[0].alpha - b[0].alpha).abs().max() > 1e-3


def test_drawn_differs_only_for_gaussians_that_reach_no_pixel(monkeypatch):
    """gsplat draws a Gaussian whose integer box ceil(extend sigma) overlaps the image, torch one whose footprint
    contains a pixel centre: a footprint just left of the image and a faint one between pixel centres are
    visible on gsplat only. Neither blends into any pixel, on either backend."""
    gsplat_on_cpu(monkeypatch)
    camera = axis_camera(9)
    focal, z = float(camera.K[0, 0]), 2.0
    # pixel x -1.5: sigma = sqrt(eps2d) = 0.55 px, extend 3.33: half-width 1.8, gsplat's box 2 reaches x = 0.5
    # pixel (6, 6), a pixel corner, opacity 0.0045: half-width 0.29 px, 0.71 px from the nearest centre
    centres = [[(-1.5 - 4.5) * z / focal, 0.0, z], [(6.0 - 4.5) * z / focal, (6.0 - 4.5) * z / focal, z], [0.0, 0.0, z]]
    gaussians = gaussians_at(centres, [[1e-4] * 3] * 3, [OPAQUE_LOGIT, math.log(0.0045 / 0.9955), 0.0])
    features = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    a, b = (render_and_backward(backend, gaussians, camera, features) for backend in ("torch", "gsplat"))
    assert a[0].visible.tolist() == [False, False, True] and b[0].visible.tolist() == [True, True, True]
    for out, _, f in (a, b):
        assert (out.features[..., :2] == 0).all() and (f.grad[:2] == 0).all()
        assert (out.screen_grads[:2] == 0).all() and (out.screen_absgrads[:2] == 0).all()
    assert_matches(b[0].features, a[0].features)


def test_gsplat_refuses_blending_settings_it_has_compiled_in(monkeypatch):
    gsplat_on_cpu(monkeypatch)
    gaussians, camera, features = random_scene(5, 0)
    with pytest.raises(
        ValueError,
        match="backend gsplat has min_alpha, max_alpha, min_transmittance compiled in.*got "
        "min_transmittance=0.0: use backend torch",
    ):
        rasterize(gaussians, camera, features, backend="gsplat", settings=RasterSettings(min_transmittance=0.0))


# ---------------------------------------------------------------- gsplat's real kernels, where CUDA is present


def gsplat_missing_reason() -> str | None:
    if not torch.cuda.is_available():
        return "no CUDA device here (the gsplat backend is CUDA only)"
    error = gsplat_import_error()
    return None if error is None else f"gsplat does not import ({error}); pip install 'matspray[cuda]'"


needs_gsplat = pytest.mark.skipif(gsplat_missing_reason() is not None, reason=str(gsplat_missing_reason()))


def to_cuda(gaussians: Gaussians, camera, features):
    leaves = [
        t.detach().cuda().requires_grad_(True)
        for t in (gaussians.means, gaussians.log_scales, gaussians.quats, gaussians.opacity_logits)
    ]
    return Gaussians(*leaves, gaussians.sh.cuda()), camera.to("cuda"), features.detach().cuda().requires_grad_(True)


@needs_gsplat
@pytest.mark.on_device
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gsplat_matches_torch_on_cuda(seed):
    # tolerances: both backends blend the same hits in float32, but gsplat's kernels are compiled with
    # -use_fast_math (__expf): a hit that sits on the 1/255 alpha threshold can go either way
    gaussians, camera, features = parity_scene(seed, width=24, height=20)
    results = []
    for backend in ("torch", "gsplat"):
        g, cam, f = to_cuda(gaussians, camera, features)
        out = rasterize(g, cam, f, torch.linspace(0.1, 0.7, f.shape[1], device="cuda"), backend=backend)
        loss = (
            (out.features * torch.linspace(0.5, 1.5, f.shape[1], device="cuda")).sum()
            + out.alpha.sum()
            + 0.1 * out.depth.sum()
        )
        loss.backward()
        results.append((out, g, f))
    (a, ga, fa), (b, gb, fb) = results
    torch.testing.assert_close(b.features, a.features, atol=2e-3, rtol=1e-3)
    torch.testing.assert_close(b.alpha, a.alpha, atol=2e-3, rtol=1e-3)
    torch.testing.assert_close(b.depth, a.depth, atol=1e-2, rtol=1e-3)
    for x, y in ((ga.means, gb.means), (ga.opacity_logits, gb.opacity_logits), (fa, fb)):
        torch.testing.assert_close(y.grad, x.grad, atol=2e-2, rtol=2e-2)


def sh_scene(seed: int, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    means = (torch.randn(200, 3, generator=g) * 0.5).to(device).requires_grad_(True)
    sh = (torch.randn(200, 16, 3, generator=g) * 0.3).to(device).requires_grad_(True)
    gaussians = Gaussians(means, torch.zeros(200, 3, device=device), torch.ones(200, 4, device=device),
                          torch.zeros(200, device=device), sh)  # fmt: skip
    return gaussians, Camera.look_at([0.5, -3.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.8, 16, 16).to(device)


def sh_colours_and_gradients(gaussians: Gaussians, camera: Camera, backend: str, degree: int):
    from matspray.render.backend import rendering_with
    from matspray.render.shade.sh import sh_colors

    with rendering_with(backend):
        colours = sh_colors(gaussians, camera, degree)
    weights = torch.linspace(-1.0, 1.0, colours.numel(), device=colours.device).reshape(colours.shape)
    inputs = [gaussians.means, gaussians.sh]
    grads = torch.autograd.grad((colours * weights).sum(), inputs, allow_unused=True)  # degree 0: not on the means
    return colours.detach(), *(torch.zeros_like(x) if g is None else g for g, x in zip(grads, inputs))


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_sh_colour_by_gsplat_is_ours(monkeypatch, degree):
    # backend gsplat takes the SH colour from gsplat's fused kernels (here its torch reference): the same colours
    # and gradients, to the means through the view directions too
    gsplat_on_cpu(monkeypatch)
    gaussians, camera = sh_scene(degree)
    ours = sh_colours_and_gradients(gaussians, camera, "torch", degree)
    theirs = sh_colours_and_gradients(gaussians, camera, "gsplat", degree)
    for a, b in zip(theirs, ours):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)


@needs_gsplat
@pytest.mark.on_device
def test_sh_colour_by_gsplat_is_ours_on_cuda():
    gaussians, camera = sh_scene(0, "cuda")
    ours = sh_colours_and_gradients(gaussians, camera, "torch", 3)
    theirs = sh_colours_and_gradients(gaussians, camera, "gsplat", 3)
    for a, b in zip(theirs, ours):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)
