"""`bilinear_sample` against `grid_sample` (values and both gradients), its gradcheck, and its use by the
environment maps' lookups on a GPU."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from matspray.render.shade.bilinear import bilinear_sample, grid_sample_border
from matspray.render.shade.envmap import EnvironmentMap


def _points(generator, count: int, dtype=torch.float64) -> torch.Tensor:  # [P, 2]
    """Random points inside and beyond [-1, 1], with some exactly on the borders and on texel centres."""
    inside = torch.rand(count, 2, generator=generator, dtype=dtype) * 2.4 - 1.2
    edges = torch.tensor([[-1.0, 0.3], [1.0, -0.2], [0.25, 1.0], [0.5, -1.0], [-1.0, -1.0], [0.0, 0.0]], dtype=dtype)
    return torch.cat([inside, edges])


def _reference(image, grid, grad):
    image = image.detach().clone().requires_grad_(True)
    grid = grid.detach().clone().requires_grad_(True)
    out = grid_sample_border(image, grid)
    out.backward(grad)
    return out.detach(), image.grad, grid.grad


@pytest.mark.parametrize("replicas", [1, 3, 64])
@pytest.mark.parametrize("size", [(1, 7), (5, 6), (9, 18)])
def test_values_and_gradients_equal_grid_sample(replicas, size):
    generator = torch.Generator().manual_seed(replicas * 100 + size[0])
    image = torch.randn(1, 4, *size, generator=generator, dtype=torch.float64)
    grid = _points(generator, 500)
    grad = torch.randn(4, grid.shape[0], generator=generator, dtype=torch.float64)
    want, want_image, want_grid = _reference(image, grid, grad)
    image.requires_grad_(True)
    grid.requires_grad_(True)
    got = bilinear_sample(image, grid, replicas)
    got.backward(grad)
    torch.testing.assert_close(got, want, rtol=0, atol=0)
    torch.testing.assert_close(image.grad, want_image, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(grid.grad, want_grid, rtol=1e-12, atol=1e-12)


def test_gradcheck():
    generator = torch.Generator().manual_seed(3)
    image = torch.randn(1, 2, 4, 5, generator=generator, dtype=torch.float64, requires_grad=True)
    # away from texel edges, where the bilinear lookup is not differentiable
    grid = (torch.rand(30, 2, generator=generator, dtype=torch.float64) * 1.8 - 0.9).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda i, g: bilinear_sample(i, g, 4), (image, grid))


def test_float32_sums_close_to_grid_sample():
    """The copies' sums are the same sums in another order: float32 rounding apart."""
    generator = torch.Generator().manual_seed(5)
    image = torch.randn(1, 9, 9, 18, generator=generator)
    grid = torch.rand(100_000, 2, generator=generator) * 2 - 1
    grad = torch.randn(9, grid.shape[0], generator=generator)
    _, want_image, _ = _reference(image, grid, grad)
    image.requires_grad_(True)
    bilinear_sample(image, grid).backward(grad)
    torch.testing.assert_close(image.grad, want_image, rtol=1e-4, atol=1e-3)


@pytest.mark.on_device
def test_environment_lookups_use_it_on_a_gpu(device, monkeypatch):
    """On CUDA the environment maps' lookups take `bilinear_sample` (and give grid_sample's gradients); on the CPU,
    grid_sample's own backward."""
    from matspray.render.shade import envmap

    calls = []
    monkeypatch.setattr(envmap, "bilinear_sample", lambda *a: calls.append(1) or bilinear_sample(*a))
    light = EnvironmentMap.constant(0.5, height=8, device=device)
    with torch.no_grad():
        light.log_map.add_(torch.randn(light.log_map.shape, generator=torch.Generator().manual_seed(0)).to(device))
    directions = F.normalize(torch.randn(4000, 3, generator=torch.Generator().manual_seed(1)), dim=-1).to(device)
    roughness = torch.rand(4000, generator=torch.Generator().manual_seed(2)).to(device)
    specular, diffuse = light.prefilter().lookup(directions, roughness, directions)
    (specular.square().sum() + diffuse.sum()).backward()
    assert bool(calls) == (device.type == "cuda")
    got = light.log_map.grad.clone()
    light.log_map.grad = None
    monkeypatch.setattr(envmap, "bilinear_sample", lambda image, grid: grid_sample_border(image, grid))
    specular, diffuse = light.prefilter().lookup(directions, roughness, directions)
    (specular.square().sum() + diffuse.sum()).backward()
    torch.testing.assert_close(got, light.log_map.grad, rtol=1e-4, atol=1e-4)
