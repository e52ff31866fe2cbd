import pytest
import torch

from matspray.render.backend import rendering_with
from matspray.render.raster.gbuffer import FrozenViews, view_blend
from matspray.render.raster.rasterize import rasterize
from tests.test_rasterize import random_scene

PACKED_ATOL = 1e-6 + 40 * 0.5 / 65535  # frozen views' packed weights (16 bits) of at most 40 Gaussians in a pixel


def test_frozen_views_match_the_rasterizer_values_and_gradients():
    gaussians, camera = random_scene(40, 0, width=24, height=20)[:2]
    features = torch.rand(len(gaussians), 4, requires_grad=True)
    frozen = FrozenViews(gaussians, [camera])
    image, alpha = frozen.render(0, features)
    reference = rasterize(gaussians.detach(), camera, features)
    assert (image - reference.features).abs().max() <= PACKED_ATOL
    assert (alpha - reference.alpha).abs().max() <= PACKED_ATOL
    upstream = torch.rand_like(image)
    (grad,) = torch.autograd.grad((image * upstream).sum(), features)
    (grad_ref,) = torch.autograd.grad((reference.features * upstream).sum(), features)
    assert (grad - grad_ref).abs().max() <= 1e-5 + 12 * PACKED_ATOL  # a Gaussian's weights over 480 pixels
    assert frozen.visible(0).any()


def test_normals_are_flipped_to_face_the_camera():
    gaussians, camera = random_scene(40, 1)[:2]
    frozen = FrozenViews(gaussians, [camera])
    normals = torch.nn.functional.normalize(torch.randn(len(gaussians), 3), dim=-1)
    oriented = frozen.orient_normals(0, normals)
    assert ((oriented * (camera.center - gaussians.means)).sum(-1) >= 0).all()
    assert torch.allclose(oriented.abs(), normals.abs())


def test_sparse_blend_gradient_passes_gradcheck():
    gaussians, camera = random_scene(12, 2, width=8, height=6)[:2]
    frozen = FrozenViews(gaussians, [camera])
    features = torch.rand(len(gaussians), 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda f: frozen.render(0, f)[0], (features,))
    assert frozen.render(0, features)[0].abs().sum() > 0  # the view sees some of the Gaussians


def test_coverage_is_each_gaussians_share_of_the_rendered_alpha():
    gaussians, camera = random_scene(40, 3, width=24, height=20)[:2]
    frozen = FrozenViews(gaussians, [camera])
    _, alpha = frozen.render(0, torch.ones(len(gaussians), 1))
    assert torch.allclose(frozen.coverage[0].sum(), alpha.sum(), rtol=1e-5)
    assert (frozen.coverage[0][frozen.visible(0)] > 0).all() and (frozen.coverage[0][~frozen.visible(0)] == 0).all()


@pytest.mark.parametrize("seed, count, width, height", [(0, 60, 40, 30), (3, 400, 70, 50), (5, 1, 16, 16)])
def test_numba_blend_matrix_is_torchs_in_csr_order_with_its_coverage_and_visible_gaussians(seed, count, width, height):
    """The compiled blend matrix (placed pixel by pixel from the forward's record, each pixel's hits put in Gaussian
    order) is the torch backend's hits sorted: the same rows and columns, the weights within float32 rounding."""
    pytest.importorskip("numba")
    from matspray.render.numba.backend import numba_view_blend

    gaussians, camera = random_scene(count, seed, width=width, height=height)[:2]
    crow, columns, weights, coverage, visible = numba_view_blend(gaussians, camera)
    torch_crow, torch_columns, torch_weights, torch_coverage, torch_visible = view_blend(gaussians, camera, "torch")
    assert torch.equal(crow, torch_crow) and torch.equal(columns, torch_columns) and torch.equal(visible, torch_visible)
    assert crow.dtype == columns.dtype == visible.dtype == torch.int64 and weights.dtype == torch.float32
    torch.testing.assert_close(weights, torch_weights, rtol=0, atol=1e-6)
    torch.testing.assert_close(coverage, torch_coverage, rtol=1e-5, atol=1e-6)
    assert len(weights) > 0 and (weights > 0).all()


def test_frozen_views_use_the_compiled_weights_on_backend_numba(monkeypatch):
    pytest.importorskip("numba")
    from matspray.render.numba import backend as numba_backend

    gaussians, camera = random_scene(40, 0, width=24, height=20)[:2]
    features = torch.rand(len(gaussians), 3)
    with rendering_with("numba") as use:
        image, _ = FrozenViews(gaussians, [camera]).render(0, features)
    assert use.used().get("numba", 0) >= 1 and "torch" not in use.used()
    assert torch.allclose(image, rasterize(gaussians, camera, features).features, atol=PACKED_ATOL)
    monkeypatch.setattr(numba_backend, "RECORD_BUDGET", 10)  # a record too large: torch's weights instead
    with rendering_with("numba") as use:
        again, _ = FrozenViews(gaussians, [camera]).render(0, features)
    assert "torch" in use.used() and torch.allclose(again, image, atol=1e-5)
