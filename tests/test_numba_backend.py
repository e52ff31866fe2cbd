"""Backend numba against backend torch (the readable reference): images, alpha, depths, every gradient, absgrad,
on random scenes and on the edge cases (opaque and nearly transparent Gaussians, Gaussians behind the camera,
footprints across tile borders, an empty image, sizes that are not multiples of 16); bitwise determinism; the
compiled projection against `project_gaussians` and `_setup` (bits, gradients, the near plane, degenerate
footprints); how `auto` chooses it; what a pipeline stage records; the one-line compile notice and numba's cache."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import threading

import numpy as np
import pytest
import torch

from matspray.data.camera import Camera
from matspray.errors import SettingError
from matspray.gaussians import Gaussians
from matspray.method.config import build_config
from matspray.method.pipeline import Pipeline
from matspray.render.backend import BACKENDS, rendering_with, resolve_backend
from matspray.render.raster.rasterize import _setup, rasterize
from matspray.render.settings import RasterSettings
from tests.scenes import stacked_opaque_gaussians
from tests.test_rasterize import random_scene

PARAMS = ("means", "log_scales", "quats", "opacity_logits")


def render_and_backward(backend, gaussians, camera, features, background=None, settings=RasterSettings(), seed=0):
    """Render with `backend`, backpropagate a loss that weights every channel and pixel differently; returns the
    output and the gradients of the Gaussians' parameters and the features (fresh leaves each call)."""
    leaves = [getattr(gaussians, name).detach().clone().requires_grad_(True) for name in PARAMS]
    g = Gaussians(*leaves, gaussians.sh.detach())
    feats = features.detach().clone().requires_grad_(True)
    out = rasterize(g, camera, feats, background, backend=backend, settings=settings, absgrad=True)
    out.retain_screen_grads()
    weights = torch.rand(out.features.shape, generator=torch.Generator().manual_seed(seed), dtype=out.features.dtype)
    loss = (out.features * weights).sum() + out.alpha.square().sum() + 0.3 * out.depth.sum() + out.expected_depth.sum()
    loss.backward()
    grads = {name: leaf.grad for name, leaf in zip(PARAMS, leaves)}
    grads["features"] = feats.grad
    return out, grads


def assert_backends_agree(gaussians, camera, features, background=None, settings=RasterSettings()):
    ref, ref_grads = render_and_backward("torch", gaussians, camera, features, background, settings)
    out, grads = render_and_backward("numba", gaussians, camera, features, background, settings)
    assert out.backend == "numba" and ref.backend == "torch"
    assert out.pixel_hits == ref.pixel_hits
    for name in ("features", "alpha", "depth", "expected_depth"):
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), atol=1e-5, rtol=1e-5, msg=name)
    torch.testing.assert_close(out.radii, ref.radii, atol=0, rtol=0)
    torch.testing.assert_close(out.means2d, ref.means2d, atol=0, rtol=0)
    for name, grad in ref_grads.items():
        scale = grad.abs().max().clamp_min(1e-12)  # 1e-4 relative to the largest gradient of the parameter
        torch.testing.assert_close(grads[name] / scale, grad / scale, atol=1e-4, rtol=0, msg=name)
    for name in ("screen_grads", "screen_absgrads"):
        mine, theirs = getattr(out, name), getattr(ref, name)
        scale = theirs.abs().max().clamp_min(1e-12)
        torch.testing.assert_close(mine / scale, theirs / scale, atol=1e-4, rtol=0, msg=name)
    return ref, out


@pytest.mark.parametrize("seed, width, height", [(0, 16, 12), (1, 53, 37), (2, 48, 32), (3, 17, 65)])
def test_matches_torch_on_random_scenes(seed, width, height):
    gaussians, camera, features = random_scene(300, seed, width=width, height=height)
    ref, _ = assert_backends_agree(gaussians, camera, features, torch.tensor([0.2, 0.5, 1.0]))
    assert ref.alpha.max() > 0.9 and (ref.alpha < 0.5).any() and ref.pixel_hits > 1000


def test_the_backward_without_the_forwards_record_matches_torch(monkeypatch):
    """A render whose record of hits would pass RECORD_BUDGET runs the backward that finds its hits again: the same
    gradients (that its compilation is said once: test_compiling_is_said_once_and_the_cache_is_reused, on a fresh
    cache)."""
    from matspray.render.numba import backend as numba_backend

    numba_backend.ensure_compiled(np.float32)  # the warm-up's own render keeps its record (the test alone in a process)
    monkeypatch.setattr(numba_backend, "RECORD_BUDGET", -1)
    calls = []
    unrecorded = numba_backend._unrecorded_backward
    monkeypatch.setattr(numba_backend, "_unrecorded_backward", lambda *a: calls.append(1) or unrecorded(*a))
    for seed, width, height in ((1, 53, 37), (5, 40, 33)):
        gaussians, camera, features = random_scene(300, seed, width=width, height=height)
        assert_backends_agree(gaussians, camera, features, torch.tensor([0.2, 0.5, 1.0]))
    early = stacked_opaque_gaussians()
    assert_backends_agree(*early)
    assert len(calls) == 3


def test_opaque_and_nearly_transparent_gaussians():
    gaussians, camera, features = random_scene(200, 4, width=40, height=33, max_opacity=1.0)
    logits = gaussians.opacity_logits.clone()
    logits[:40] = 20.0  # opacity 1 in float32: alpha clamps at max_alpha, and what is behind stops early
    logits[40:80] = torch.logit(torch.tensor(0.0045))  # just above min_alpha at the centre only
    logits[80:90] = torch.logit(torch.tensor(0.003))  # below min_alpha everywhere: never drawn
    gaussians.opacity_logits = logits
    ref, out = assert_backends_agree(gaussians, camera, features)
    assert (out.radii[80:90] == 0).all()


def test_early_termination_and_other_settings():
    """Eight nearly opaque Gaussians stacked on the optical axis (as tests/test_rasterize.py), with the default
    stop, without it, and with other alpha bounds."""
    gaussians, camera, features = stacked_opaque_gaussians()
    _, out = assert_backends_agree(gaussians, camera, features)
    assert out.features[3:5, 3:5, -1].max() == 0  # the four central pixels stop before the last one
    for settings in (RasterSettings(min_transmittance=0.0), RasterSettings(min_alpha=0.05, max_alpha=0.9)):
        assert_backends_agree(gaussians, camera, features, settings=settings)


def test_gaussians_behind_the_camera_get_nothing():
    gaussians, camera, features = random_scene(60, 6, width=24, height=20)
    means = gaussians.means.clone()
    means[:10] = camera.center + 2.0 * (camera.center - means[:10])  # behind the camera
    means[10] = camera.center  # on it
    gaussians.means = means
    _, out = assert_backends_agree(gaussians, camera, features)
    assert (out.radii[:11] == 0).all()


def test_footprints_across_tile_borders():
    """Large Gaussians centred on tile corners and edges of a 40 x 40 image (tiles at 16 and 32)."""
    centres = [(16.0, 16.0), (32.0, 15.5), (15.5, 32.5), (0.0, 0.0), (39.9, 20.0), (24.0, 16.2)]
    camera = Camera.look_at([0.0, 0.0, -4.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], math.radians(40), 40, 40)
    K, R, t = camera.K, camera.viewmat[:3, :3], camera.viewmat[:3, 3]
    depth = 4.0 + 0.1 * torch.arange(len(centres), dtype=torch.float32)
    pixels = torch.tensor(centres)
    in_camera = torch.stack(
        [(pixels[:, 0] - K[0, 2]) / K[0, 0] * depth, (pixels[:, 1] - K[1, 2]) / K[1, 1] * depth, depth], dim=1
    )
    means = (in_camera - t) @ R  # R^T (x - t), row by row: the points that project onto `centres`
    n = len(centres)
    g = torch.Generator().manual_seed(3)
    gaussians = Gaussians(
        means,
        torch.log(torch.full((n, 3), 0.3) * (0.5 + torch.rand(n, 3, generator=g))),
        torch.randn(n, 4, generator=g),
        torch.logit(torch.linspace(0.4, 0.9, n)),
        torch.zeros(n, 1, 3),
    )
    ref, out = assert_backends_agree(gaussians, camera, torch.rand(n, 4, generator=g))
    torch.testing.assert_close(out.means2d, pixels, atol=1e-3, rtol=0)
    assert out.visible.all() and ref.alpha[15:17, 15:17].min() > 0.1  # the footprints do reach across the borders


def test_empty_image():
    gaussians, camera, features = random_scene(10, 7, width=20, height=18)
    gaussians.means = camera.center + 2.0 * (camera.center - gaussians.means)  # all behind the camera
    out, grads = render_and_backward("numba", gaussians, camera, features, torch.tensor([0.1, 0.2, 0.3]))
    assert out.pixel_hits == 0 and (out.alpha == 0).all() and (out.depth == 0).all()
    torch.testing.assert_close(out.features, torch.tensor([0.1, 0.2, 0.3]).expand(18, 20, 3))
    assert all((grad == 0).all() for grad in grads.values())


def test_deterministic_run_to_run_and_across_thread_counts():
    gaussians, camera, features = random_scene(400, 8, width=61, height=47)
    threads = torch.get_num_threads()
    runs = []
    try:
        for count in (2, 2, 1):
            torch.set_num_threads(count)  # numba takes as many threads as torch
            out, grads = render_and_backward("numba", gaussians, camera, features)
            runs.append([out.features, out.alpha, out.depth, out.screen_absgrads, *grads.values()])
    finally:
        torch.set_num_threads(threads)
    for other in runs[1:]:
        for a, b in zip(runs[0], other):
            assert torch.equal(a, b)


def test_gradcheck_float64():
    """The kernels in float64 against finite differences (as tests/test_rasterize.py checks backend torch)."""
    gaussians, camera, features = random_scene(4, 5, dtype=torch.float64, width=7, height=6, max_opacity=0.8)
    gaussians.log_scales = gaussians.log_scales + math.log(2.5)  # footprints of a few pixels, overlapping
    background = torch.tensor([0.3, 0.1, 0.7], dtype=torch.float64)

    def render(means, log_scales, quats, opacity_logits, feats):
        out = rasterize(
            Gaussians(means, log_scales, quats, opacity_logits, gaussians.sh),
            camera,
            feats,
            background,
            backend="numba",
        )
        return out.features, out.alpha, out.depth

    inputs = tuple(
        t.clone().requires_grad_(True)
        for t in (gaussians.means, gaussians.log_scales, gaussians.quats, gaussians.opacity_logits, features.double())
    )
    assert render(*inputs)[1].max() > 0.5 and render(*inputs)[0].dtype == torch.float64
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


# ---------------------------------------------------------------- the compiled projection


def compiled_projection(gaussians, camera, settings=RasterSettings()):
    """means2d, conics, depths (differentiable), radii, boxes from backend numba's projection Function."""
    from matspray.render.numba import backend as numba_backend

    dtype = gaussians.means.dtype
    np_dtype = np.float64 if dtype == torch.float64 else np.float32
    numba_backend.ensure_compiled(np_dtype)
    layout = numba_backend._Layout(camera, settings, np_dtype)
    means2d, conics, depths = numba_backend._NumbaProjection.apply(
        gaussians.means, gaussians.scales, gaussians.quats, gaussians.opacities, layout
    )
    return means2d, conics, depths, layout.radii, torch.from_numpy(layout.boxes)


def hard_scene(near=0.01, seed=9):
    """Random Gaussians plus the hard cases, for a camera at the origin looking down +z (identity viewmat, so the
    camera z of a centre is exactly its z): centres exactly on the near plane, just in front of it, just behind it,
    behind the camera; needles and flat discs (scales 1e-20, degenerate without eps2d), a zero quaternion, huge
    and tiny scales, and centres far outside the view (the Jacobian's clamp)."""
    gaussians, _, _ = random_scene(200, seed, width=40, height=30)
    means = gaussians.means.clone() * 2.0
    means[:, 2] = 3.0 + means[:, 2]
    log_scales, quats = gaussians.log_scales.clone(), gaussians.quats.clone()
    means[0, 2] = near  # on the near plane: not drawn (z > near is required)
    means[1, 2] = near * 1.01
    means[2, 2] = near * 0.99
    means[3:6, 2] = torch.tensor([-1.0, -0.5, 0.0])
    log_scales[6] = torch.tensor([0.0, -46.0, -46.0])  # a needle (scales 1e-20)
    log_scales[7] = torch.tensor([-1.0, -1.0, -46.0])  # a flat disc
    log_scales[8] = torch.tensor([-46.0, -46.0, -46.0])
    quats[9] = 0.0
    log_scales[10] = torch.tensor([3.0, 2.0, 1.0])
    means[11:14, 0] = torch.tensor([40.0, -60.0, 25.0])  # far outside the view
    means[11:14, 1] = torch.tensor([-30.0, 5.0, 80.0])
    gaussians = Gaussians(means, log_scales, quats, gaussians.opacity_logits, gaussians.sh)
    K = torch.tensor([[40.0, 0.0, 20.0], [0.0, 40.0, 15.0], [0.0, 0.0, 1.0]])
    return gaussians, Camera(K=K, viewmat=torch.eye(4), width=40, height=30)


@pytest.mark.parametrize("settings", [RasterSettings(), RasterSettings(eps2d=0.0, near=0.2)])
def test_compiled_projection_is_setups_bits(settings):
    for gaussians, camera in (hard_scene(settings.near), random_scene(500, 3, width=53, height=37)[:2]):
        ref = _setup(gaussians, camera, settings)
        means2d, conics, depths, radii, boxes = compiled_projection(gaussians, camera, settings)
        assert torch.equal(means2d, ref.proj.means2d) and torch.equal(depths, ref.proj.depths)
        valid = ref.proj.valid  # invalid ones hold placeholder conics (both backends the same ones, but no more)
        assert (
            torch.equal(conics[valid], ref.proj.conics[valid])
            and torch.equal(radii, ref.radii)
            and torch.equal(boxes, ref.boxes)
        )
    ref = _setup(*hard_scene(settings.near), settings)
    assert not ref.proj.valid[[0, 2, 3, 4, 5]].any() and ref.proj.valid[1]  # the near plane and behind the camera
    if settings.eps2d == 0.0:
        assert not ref.proj.valid[[6, 8]].any()  # singular footprints


@pytest.mark.parametrize("settings", [RasterSettings(), RasterSettings(eps2d=0.0, near=0.2)])
def test_compiled_projection_gradients(settings):
    """Every output weighted at random (the placeholders of invalid Gaussians too, which torch differentiates as
    written), the gradients of means, log_scales and quats within 1e-4 of the largest."""
    for gaussians, camera in (hard_scene(settings.near), random_scene(500, 3, width=53, height=37)[:2]):
        grads = []
        for compiled in (False, True):
            leaves = [
                t.detach().clone().requires_grad_(True)
                for t in (gaussians.means, gaussians.log_scales, gaussians.quats)
            ]
            g = Gaussians(*leaves, gaussians.opacity_logits, gaussians.sh)
            if compiled:
                means2d, conics, depths = compiled_projection(g, camera, settings)[:3]
            else:
                proj = _setup(g, camera, settings).proj
                means2d, conics, depths = proj.means2d, proj.conics, proj.depths
            gen = torch.Generator().manual_seed(1)
            loss = sum((t * torch.randn(t.shape, generator=gen)).sum() for t in (means2d, conics, depths))
            loss.backward()
            grads.append([leaf.grad for leaf in leaves])
        for ref, mine, name in zip(*grads, ("means", "log_scales", "quats")):
            assert torch.isfinite(mine).all(), name
            scale = ref.abs().max().clamp_min(1e-12)
            torch.testing.assert_close(mine / scale, ref / scale, atol=1e-4, rtol=0, msg=name)


def test_compiled_projection_gradcheck_float64():
    gaussians, camera = hard_scene()
    keep = torch.tensor(
        [1, 7, 9, 11, 20, 21, 22, 23]
    )  # just in front of the near plane, a disc, q = 0, clamped, ordinary
    sub = gaussians.subset(keep).to(dtype=torch.float64)
    sub.quats[2] = torch.tensor([0.3, -0.2, 0.1, 0.5], dtype=torch.float64)  # gradcheck needs |q| > 0

    def project(means, log_scales, quats):
        return compiled_projection(Gaussians(means, log_scales, quats, sub.opacity_logits, sub.sh), camera)[:3]

    inputs = tuple(t.clone().requires_grad_(True) for t in (sub.means, sub.log_scales, sub.quats))
    assert torch.autograd.gradcheck(project, inputs, eps=1e-7, atol=1e-5, rtol=1e-4)


# ---------------------------------------------------------------- choosing it, counting it, compiling it


def test_auto_on_the_cpu_is_numba_and_torch_stays_available():
    assert "numba" in BACKENDS
    assert resolve_backend("auto", "cpu") == "numba" and resolve_backend("numba", "cpu") == "numba"
    assert resolve_backend("torch", "cpu") == "torch"
    with pytest.raises(SettingError, match="backend: numba renders on the CPU only"):
        resolve_backend("numba", "cuda")
    with rendering_with("numba") as use:
        gaussians, camera, features = random_scene(5, 0)
        assert rasterize(gaussians, camera, features).backend == "numba"
        assert rasterize(gaussians, camera, features, backend="torch").backend == "torch"
    assert use.used() == {"numba": 1, "torch": 1}


def test_a_stage_record_counts_numba_renders(tiny_object, tmp_path):
    config = build_config("test", predictor="simulated", device="cpu", backend="auto", visibility=None)
    with Pipeline(tiny_object, tmp_path / "run", config, progress=False, log=lambda _: None) as pipeline:
        assert pipeline.backend == "numba"
        pipeline.geometry()
    record = json.loads((tmp_path / "run" / "geometry" / "stage.json").read_text())
    assert record["backend"] == "numba" and set(record["renders"]) == {"numba"} and record["renders"]["numba"] >= 60


MISSES = (  # after the work: numba's cache misses (compilations) of every kernel, by module and name, as JSON, and
    # whether the kernel is inlined into its callers (inline="always": never compiled on its own)
    "import atexit, importlib, json\nfrom numba.core.dispatcher import Dispatcher\n"
    "def misses():\n"
    "    modules = [importlib.import_module('matspray.render.numba.' + name) for name in "
    "('kernels', 'projection', 'sh', 'normals', 'rays')]\n"
    "    print(json.dumps({f'{m.__name__.split(\".\")[-1]}.{n}': [sum(f.stats.cache_misses.values()), "
    "f.targetoptions.get('inline') == 'always'] for m in modules for n, f in vars(m).items() "
    "if isinstance(f, Dispatcher) and f.__module__ == m.__name__}))\n"
    "atexit.register(misses)\n"
)


COMPILE_KERNELS = "import runpy\nrunpy.run_module('matspray.render.numba.compile', run_name='__main__')\n"
COMPILE_TEST = "test_compiling_is_said_once_and_the_cache_is_reused"
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module", autouse=True)
def fresh_compilation(request, tmp_path_factory):
    """The first process of the compile test below, `python -m matspray.render.numba.compile` into a fresh cache
    folder, started as this module starts (when that test is to run): its minute of compiling on one core runs beside
    the module's other tests, which compile the float64 kernels in this process meanwhile. (cache folder, Popen)"""
    if not any(item.name == COMPILE_TEST for item in request.session.items):
        yield None
        return
    cache = tmp_path_factory.mktemp("numba-cache")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    command = [sys.executable, "-c", MISSES + COMPILE_KERNELS]
    process = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
    yield cache, process
    if process.poll() is None:  # the test did not run (deselected by a marker) or failed before waiting for it
        process.kill()
        process.communicate()


@pytest.mark.slow  # compiles the kernels from scratch (about a minute), then loads them
def test_compiling_is_said_once_and_the_cache_is_reused(fresh_compilation):
    """A fresh cache folder: `python -m matspray.render.numba.compile` (what `make demo` runs while it installs)
    compiles every kernel of the warm-up once and says so in one line; a render in a later process loads them from
    the cache and says nothing, and its renders past RECORD_BUDGET compile the unrecorded backward once (said once).
    The compilations are numba's own count of cache misses per kernel."""
    script = (
        "import torch; from tests.test_rasterize import random_scene\n"
        "from matspray.render.raster.rasterize import rasterize\n"
        "from matspray.render.numba import backend as numba_backend\n"
        "g, c, f = random_scene(20, 0)\n"
        "for _ in range(2): rasterize(g, c, f, backend='numba')\n"
        "numba_backend.RECORD_BUDGET = -1  # from here the backward finds the hits again\n"
        "for _ in range(2):\n"
        "    f = f.clone().requires_grad_(True)\n"
        "    rasterize(g, c, f, backend='numba').features.sum().backward()\n"
    )
    cache, first = fresh_compilation
    out, err = first.communicate(timeout=600)
    assert first.returncode == 0, err
    later = subprocess.run(
        [sys.executable, "-c", MISSES + script],
        env=dict(os.environ, NUMBA_CACHE_DIR=str(cache)),
        capture_output=True,
        text=True,
        timeout=600,
        cwd=REPO,
    )
    assert later.returncode == 0, later.stderr
    said = [[line for line in e.splitlines() if line.startswith("numba:")] for e in (err, later.stderr)]
    compiled = [json.loads(o.splitlines()[-1]) for o in (out, later.stdout)]
    unrecorded = "kernels.backward"
    # the float32 warm-up compiles each kernel once (those inlined into their callers never on their own), all but
    # the unrecorded backward and float64's depth sort; the later process loads every one of them from the cache and
    # compiles the unrecorded backward, once
    kernels = {name: inlined for name, (_, inlined) in compiled[0].items()}
    later = {unrecorded, "projection._merge_order"}
    assert len(kernels) > 10 and later <= set(kernels) and any(kernels.values())
    assert {name: count for name, (count, _) in compiled[0].items()} == {
        name: int(not inlined and name not in later) for name, inlined in kernels.items()
    }, compiled[0]
    assert {name: count for name, (count, _) in compiled[1].items()} == {
        name: int(name == unrecorded) for name in kernels
    }, compiled[1]
    assert (
        len(said[0]) == 2
        and "(float32: rasterizer, SH colour, normals, lifting's rays, frozen views)" in said[0][0]
        and str(cache) in said[0][0]
        and said[0][1].startswith("numba: the CPU kernels are ready")
    )
    assert len(said[1]) == 1 and "compiled the backward kernel for renders of more than -1 hits" in said[1][0], said[1]


def test_kernels_compiled_in_the_background_are_waited_for_once(monkeypatch):
    """compile_in_background starts one thread per dtype; ensure_compiled from another thread waits for it and then
    finds the kernels ready, marked ready only once the warm-up has run (they are loaded from the cache here: the
    test is about the waiting)."""
    from matspray.render.numba import backend as numba_backend

    monkeypatch.setattr(numba_backend, "_READY", set())
    monkeypatch.setattr(numba_backend, "_WARMING", {})
    started, release, finished = threading.Event(), threading.Event(), threading.Event()
    warm_up = numba_backend._warm_up

    def slow_warm_up(np_dtype):
        started.set()
        release.wait(30)
        warm_up(np_dtype)
        finished.set()

    monkeypatch.setattr(numba_backend, "_warm_up", slow_warm_up)
    numba_backend.compile_in_background(np.float32)
    numba_backend.compile_in_background(np.float32)  # a second request starts no second thread
    assert started.wait(30) and len(numba_backend._WARMING) == 1
    waiter = threading.Thread(target=numba_backend.ensure_compiled, args=(np.float32,))
    waiter.start()
    waiter.join(0.5)
    assert waiter.is_alive()  # waiting for the background compilation
    assert "float32" not in numba_backend._READY  # not ready while the warm-up runs
    release.set()
    waiter.join(60)
    assert not waiter.is_alive() and finished.is_set() and "float32" in numba_backend._READY


def test_a_second_thread_waits_for_a_warm_up_in_progress_and_a_failed_one_is_not_ready(monkeypatch):
    """Two threads call ensure_compiled at once (no background thread): the second waits for the first's warm-up;
    a warm-up that raises leaves the dtype not ready, so the next call warms up again."""
    from matspray.render.numba import backend as numba_backend

    monkeypatch.setattr(numba_backend, "_READY", set())
    monkeypatch.setattr(numba_backend, "_WARMING", {})
    started, release, runs = threading.Event(), threading.Event(), []

    def failing_warm_up(np_dtype):
        runs.append(np_dtype)
        started.set()
        release.wait(30)
        raise RuntimeError("a warm-up that fails")

    monkeypatch.setattr(numba_backend, "_warm_up", failing_warm_up)
    failed = []
    first = threading.Thread(
        target=lambda: failed.append(pytest.raises(RuntimeError, numba_backend.ensure_compiled, np.float32))
    )
    first.start()
    assert started.wait(30)
    second = threading.Thread(
        target=lambda: failed.append(pytest.raises(RuntimeError, numba_backend.ensure_compiled, np.float32))
    )
    second.start()
    second.join(0.5)
    assert second.is_alive() and "float32" not in numba_backend._READY  # the second waits for the first
    release.set()
    first.join(30)
    second.join(30)
    assert not first.is_alive() and not second.is_alive()
    assert len(failed) == 2 and len(runs) == 2 and "float32" not in numba_backend._READY  # each tried, none ready


def test_a_kernel_s_compilation_is_said_once_per_argument_types_and_later_calls_only_run_it(capsys, monkeypatch):
    import numba

    from matspray.render.numba import kernels as numba_kernels

    @numba.njit
    def doubled(x):
        return x * 2

    counted = []
    cache_misses = numba_kernels.cache_misses
    monkeypatch.setattr(numba_kernels, "cache_misses", lambda d: counted.append(1) or cache_misses(d))
    ints, floats = np.arange(3), np.ones(2)
    results = [numba_kernels.call_saying_compiled(doubled, "doubling", a) for a in (ints, ints, floats, floats)]
    said = [line for line in capsys.readouterr().err.splitlines() if line.startswith("numba:")]
    assert [r.tolist() for r in results] == [[0, 2, 4], [0, 2, 4], [2.0, 2.0], [2.0, 2.0]]
    assert len(said) == 2 and all(line.startswith("numba: compiled doubling in ") for line in said), said
    assert len(counted) == 4  # before and after the first call of each argument type only
