import torch

from matspray.render.gbuffer import FrozenViews
from matspray.render.rasterize import rasterize
from tests.test_rasterize import random_scene


def test_frozen_views_match_the_rasterizer_values_and_gradients():
    gaussians, camera = random_scene(40, 0, width=24, height=20)[:2]
    features = torch.rand(len(gaussians), 4, requires_grad=True)
    frozen = FrozenViews(gaussians, [camera])
    image, alpha = frozen.render(0, features)
    reference = rasterize(gaussians.detach(), camera, features)
    assert torch.allclose(image, reference.features, atol=1e-5)
    assert torch.allclose(alpha, reference.alpha, atol=1e-5)
    upstream = torch.rand_like(image)
    (grad,) = torch.autograd.grad((image * upstream).sum(), features)
    (grad_ref,) = torch.autograd.grad((reference.features * upstream).sum(), features)
    assert torch.allclose(grad, grad_ref, atol=1e-5)
    assert frozen.visible(0).any()


def test_normals_are_flipped_to_face_the_camera():
    gaussians, camera = random_scene(40, 1)[:2]
    frozen = FrozenViews(gaussians, [camera])
    normals = torch.nn.functional.normalize(torch.randn(len(gaussians), 3), dim=-1)
    oriented = frozen.orient_normals(0, normals)
    assert ((oriented * (camera.center - gaussians.means)).sum(-1) >= 0).all()
    assert torch.allclose(oriented.abs(), normals.abs())
