"""The Gaussian Splatting step that keeps a GPU fed: its loss terms as one function of tensors (captured in CUDA graphs
on a CUDA device, here through a stand-in that runs it as one operation each way), the camera's cached rays, the copy
that does not stall, and the counts of benchmarks.step_cost that keep the step from growing back."""

from __future__ import annotations

import pytest
import torch

from benchmarks.step_cost import graph_stand_in, measure, tiny_scene, trained_state
from matspray.data.camera import Camera
from matspray.device import host_to_device
from matspray.geometry.config import preset
from matspray.geometry.step import TERMS, ImageTerms, RunningStats, TrainingView, image_terms, training_step

# benchmarks.step_cost on the code before this step (commit e4b9a07): the GPU path's operations per Gaussian
# Splatting step, SH colour and normals by torch operations then
GEOMETRY_OPERATIONS_BEFORE = 842


def image_inputs(height: int, width: int, seed: int, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    camera = Camera.look_at([0.2, -3.0, 0.5], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.7, width, height).to(device)
    rgb = torch.rand(height, width, 3, generator=g).to(device).requires_grad_(True)
    alpha = torch.rand(height, width, generator=g).to(device).requires_grad_(True)
    normals = torch.randn(height, width, 3, generator=g).to(device).requires_grad_(True)
    depth = (2.5 + torch.rand(height, width, generator=g)).to(device).requires_grad_(True)
    srgb = torch.rand(height, width, 3, generator=g).to(device)
    mask = (torch.rand(height, width, generator=g) > 0.3).float().to(device)
    background = torch.rand(3, generator=g).to(device)
    predicted = torch.nn.functional.normalize(torch.randn(height, width, 3, generator=g), dim=-1)
    predicted = (predicted * (torch.rand(height, width, 1, generator=g) > 0.2)).to(device)  # zero: no prediction
    return (rgb, alpha, normals, depth, srgb, mask, background, camera.pixel_directions(), camera.center, predicted)


def terms_and_gradients(terms_of, tensors, weights):
    terms = terms_of(tensors, weights)
    wanted = [t for t in tensors if t.requires_grad]
    grads = torch.autograd.grad(terms[:4].sum() + 0.5 * terms[0], wanted, allow_unused=True)
    return terms.detach(), [torch.zeros_like(t) if g is None else g for g, t in zip(grads, wanted)]


@pytest.mark.parametrize(
    "weights",
    [
        (0.2, 0.5, 0.05, 0.0, 0.0),
        (0.2, 0.5, 0.0, 0.0, 0.0),
        (0.2, 0.0, 0.0, 0.0, 0.0),
        (0.2, 0.5, 0.05, 1.0, 1.0),
        (0.2, 0.5, 0.0, 0.7, 0.0),
    ],
)
def test_captured_terms_are_the_terms(weights):
    # the captured callable (here the stand-in) gives the eager terms and gradients; one capture per image size
    # and set of weights, reused after that
    captured = ImageTerms(capture=graph_stand_in)
    for seed, size in ((0, (20, 24)), (1, (20, 24)), (2, (16, 18))):
        tensors = image_inputs(*size, seed)
        eager, eager_grads = terms_and_gradients(ImageTerms(graphs=False), tensors, weights)
        terms, grads = terms_and_gradients(captured, tensors, weights)
        torch.testing.assert_close(terms, eager, rtol=0, atol=0)
        for a, b in zip(grads, eager_grads):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert len(captured.captured) == 2
    assert (eager[1] == 0) == (weights[1] == 0) and (eager[2] == 0) == (weights[2] == 0)
    assert (eager[3] == 0) == (weights[3] == 0 and weights[4] == 0)


def test_image_terms_follow_their_definitions():
    rgb, alpha, normals, depth, srgb, mask, background, directions, center, predicted = image_inputs(12, 14, 3)
    terms = image_terms(
        rgb, alpha, normals, depth, srgb, mask, background, directions, center, predicted, 0.2, 0.5, 0.05, 0.3, 0.7
    )
    target = srgb * mask[..., None] + background * (1 - mask[..., None])
    torch.testing.assert_close(terms[1], 0.5 * (alpha - mask).abs().mean())
    torch.testing.assert_close(terms[4], (rgb.clamp(0, 1) - target.clamp(0, 1)).square().mean())
    # the depth's normals from the pixel rays are those of the camera's back-projected points
    from matspray.geometry.normals import depth_normals, depth_normals_along

    camera = Camera.look_at([0.2, -3.0, 0.5], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.7, 14, 12)
    torch.testing.assert_close(depth_normals_along(depth, directions, center), depth_normals(depth, camera))


def test_a_failed_capture_is_said_and_computed_without_it(capsys):
    def broken(function, samples):
        raise RuntimeError("operation not permitted when stream is capturing")

    terms_of = ImageTerms(capture=broken)
    tensors = image_inputs(12, 14, 0)
    terms = terms_of(tensors, (0.2, 0.5, 0.05, 0.0, 0.0))
    torch.testing.assert_close(terms, ImageTerms(graphs=False)(tensors, (0.2, 0.5, 0.05, 0.0, 0.0)))
    assert "without CUDA graphs (RuntimeError: operation not permitted" in capsys.readouterr().err
    assert not terms_of.graphs


def test_camera_caches_follow_changes_in_place():
    camera = Camera.look_at([0.3, -2.0, 0.4], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.9, 10, 8)
    first = camera.pixel_directions()
    assert camera.pixel_directions() is first and camera.camtoworld is camera.camtoworld
    # brute force: the ray through pixel (i, j) hits camera depth 1 at center + direction
    origins, rays = camera.rays_through(torch.tensor([[3.5, 2.5]]))
    hit = origins[0] + rays[0] / (rays[0] @ camera.camtoworld[:3, 2])
    torch.testing.assert_close(camera.center + first[2, 3], hit)
    camera.K[0, 0] *= 2  # in place: recomputed
    assert not torch.equal(camera.pixel_directions(), first)
    camera.viewmat[0, 3] += 1.0
    torch.testing.assert_close(camera.center, torch.linalg.inv(camera.viewmat.double()).float()[:3, 3])


def test_host_to_device_on_the_cpu_is_the_tensor():
    values = torch.rand(3)
    assert host_to_device(values, "cpu") is values


def test_running_stats_name_the_first_step_that_diverged():
    from matspray.errors import NumericalError

    running = RunningStats(torch.device("cpu"))
    running.add(7, torch.tensor(1.0), torch.tensor(0.01))
    running.add(8, torch.tensor(float("nan")), torch.tensor(0.01))
    running.add(9, torch.tensor(float("inf")), torch.tensor(0.01))
    with pytest.raises(NumericalError, match="diverged at iteration 8"):
        running.check({"photometric": torch.tensor(float("nan"))})


def test_running_stats_report_the_last_loss_and_a_running_psnr_of_the_steps():
    """Squared errors of 1e-2 then 1e-3 are 20 and 30 dB; the running PSNR keeps 0.9 of the old and takes 0.1 of the
    new: 0.9 * 20 + 0.1 * 30 = 21 dB. A perfect step counts as 99 dB (its PSNR is infinite)."""
    running = RunningStats(torch.device("cpu"))
    running.add(1, torch.tensor(0.5), torch.tensor(1e-2))
    running.check({})
    assert running.loss == pytest.approx(0.5) and running.psnr == pytest.approx(20.0, abs=1e-4)
    running.add(2, torch.tensor(0.25), torch.tensor(1e-3))
    running.check({})
    assert running.loss == pytest.approx(0.25) and running.psnr == pytest.approx(21.0, abs=1e-4)
    running.add(3, torch.tensor(0.0), torch.tensor(0.0))
    running.check({})
    assert running.psnr == pytest.approx(0.9 * 21.0 + 0.1 * 99.0, abs=1e-4)


def test_a_step_reads_nothing_back_and_its_losses_are_named():
    scene = tiny_scene(torch.device("cpu"))
    config, optimizer, density, running, generator = trained_state(scene, torch.device("cpu"), 500)
    target = TrainingView.of(scene.train[0], masked=True)
    before = optimizer.params["means"].detach().clone()
    training_step(optimizer, density, running, target, config, 20_001, generator, ImageTerms(), report=True)
    assert not torch.equal(optimizer.params["means"], before)
    assert running.loss > 0 and 0 < running.psnr < 99
    assert TERMS == ("photometric", "alpha", "normal", "predicted_normal")


def test_step_counts_stay_low():
    # benchmarks.step_cost: the GPU path (graphs, gsplat's fused SH) at least 3x fewer operations than before it, and
    # no step between reports waits for the device, on either path
    gpu = measure("geometry", "gpu", torch.device("cpu"))
    cpu = measure("geometry", "cpu", torch.device("cpu"))
    assert gpu["operations"] <= GEOMETRY_OPERATIONS_BEFORE / 3, gpu["top_operations"]
    assert gpu["host_syncs"] == 0 and cpu["host_syncs"] == 0, (gpu["sync_kinds"], cpu["sync_kinds"])


@pytest.mark.on_device
def test_graphed_training_matches_eager(device):
    # on CUDA the loss terms run as CUDA graphs: the same terms and gradients as computed op by op; elsewhere both
    # are the eager terms
    tensors = image_inputs(20, 24, 0, device)
    weights = (0.2, 0.5, 0.05)
    graphed = ImageTerms()
    for _ in range(2):  # the capture, then a replay with new values
        eager, eager_grads = terms_and_gradients(ImageTerms(graphs=False), tensors, weights)
        terms, grads = terms_and_gradients(graphed, tensors, weights)
        torch.testing.assert_close(terms, eager, rtol=1e-5, atol=1e-6)
        for a, b in zip(grads, eager_grads):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)
        tensors = image_inputs(20, 24, 1, device)
    assert len(graphed.captured) == (1 if device.type == "cuda" else 0)
    assert preset("test").normal_weight > 0
