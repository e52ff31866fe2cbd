"""The compiled oriented normals (backend numba) against the torch reference: values, gradients (autograd's and
finite differences), ties between the scales, a zero quaternion, and that training renders use them under numba."""

from __future__ import annotations

import torch

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians
from matspray.geometry.normals import oriented_normals
from matspray.render.backend import rendering_with

CAMERA = Camera.look_at([0.3, -4.0, 0.8], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.6, 16, 12)


def gaussians(n: int, seed: int, dtype=torch.float64) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    log_scales = torch.randn(n, 3, generator=g)
    log_scales[:3, :] = 0.5  # ties: the first axis wins, as torch.argmin
    log_scales[3, 1:] = -1.0  # a tie between the second and the third axis
    quats = torch.randn(n, 4, generator=g)
    quats[4] = 0.0  # F.normalize leaves it at zero, and R(0) is the identity
    quats[5] *= 1e-14  # a norm below F.normalize's eps
    return Gaussians(torch.randn(n, 3, generator=g), log_scales, quats, torch.zeros(n), torch.zeros(n, 1, 3)).to(
        dtype=dtype
    )


def compiled(quats, g: Gaussians):
    from matspray.render.numba.normals import CompiledNormals

    return CompiledNormals.apply(quats, g.log_scales, g.means, CAMERA.center)


def reference(quats, g: Gaussians):
    return oriented_normals(Gaussians(g.means, g.log_scales, quats, g.opacity_logits, g.sh), CAMERA)


def test_values_and_gradients_are_the_torch_references():
    g = gaussians(300, 0)
    weights = torch.randn(300, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    grads = []
    for fn in (reference, compiled):
        quats = g.quats.clone().requires_grad_(True)
        normals = fn(quats, g)
        (normals * weights).sum().backward()
        grads.append((normals.detach(), quats.grad))
    (ref, ref_grad), (out, grad) = grads
    torch.testing.assert_close(out, ref, atol=1e-12, rtol=0)
    torch.testing.assert_close(grad, ref_grad, atol=1e-9, rtol=1e-9)
    facing = ((CAMERA.center.double() - g.means) * out).sum(-1)
    assert (facing >= 0).all() and (grad[5].abs() > 1e3).any()  # the clamped norm divides by eps, as torch


def test_float32_within_rounding_and_gradcheck():
    g32 = gaussians(200, 2, torch.float32)
    torch.testing.assert_close(compiled(g32.quats, g32), reference(g32.quats, g32), atol=1e-6, rtol=0)
    g = gaussians(12, 3)
    quats = g.quats[6:].clone().requires_grad_(True)  # away from the zero and tiny quaternions
    sub = Gaussians(g.means[6:], g.log_scales[6:], quats, g.opacity_logits[6:], g.sh[6:])
    assert torch.autograd.gradcheck(lambda q: compiled(q, sub), (quats,))


def test_training_renders_use_them_within_a_numba_block(monkeypatch):
    import numpy as np

    from matspray.geometry.evaluate import render_view
    from matspray.render.numba import normals as numba_normals
    from matspray.render.numba.backend import ensure_compiled

    ensure_compiled(np.float32)  # its warm-up calls them too
    calls = []
    original = numba_normals.CompiledNormals.apply
    monkeypatch.setattr(numba_normals.CompiledNormals, "apply", lambda *a: calls.append(1) or original(*a))
    g = gaussians(50, 4, torch.float32)
    g.log_scales = g.log_scales - 3.0
    with rendering_with("torch"):
        expected = render_view(g, CAMERA, 0).normals
    assert calls == []
    with rendering_with("numba"):
        normals = render_view(g, CAMERA, 0).normals
    assert calls == [1]
    torch.testing.assert_close(normals, expected, atol=1e-4, rtol=0)
