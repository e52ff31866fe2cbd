"""`shadow_factors` as one autograd Function (`KernelSums`) against the plain formula it replaced, kept here as the
reference: the same factors and the same gradients for the normals, the roughness and the light; and a gradcheck."""

import pytest
import torch
import torch.nn.functional as F

from matspray.render.shade.brdf import roughness_to_alpha
from matspray.render.shade.deferred import specular_direction
from matspray.render.shade.envmap import downsample_latlong
from matspray.render.shade.visibility import MAX_KAPPA, open_side, shadow_factors, visibility_directions
from tests.scenes import sky_map


def reference_shadow_factors(visibility, normals, view_dirs, roughness, light_cells):  # the formula, op by op
    rows = light_cells.shape[0]
    directions, solid_angles = visibility_directions(rows)
    directions, solid_angles = directions.to(normals.dtype), solid_angles.to(normals.dtype)
    light = light_cells.reshape(-1, 3).to(normals.dtype)
    facing = normals @ directions.t()
    side = open_side(visibility, facing, solid_angles)
    normals = normals * side
    cosine = (facing * side).clamp_min(0.0) * solid_angles
    lobe_dir = F.normalize(specular_direction(normals, view_dirs, roughness), dim=-1, eps=1e-12)
    alpha = roughness_to_alpha(roughness)
    kappa = (0.5 / alpha.square().clamp_min(1e-6)).clamp(max=MAX_KAPPA)[:, None]
    lobe = torch.exp(kappa * (lobe_dir @ directions.t() - 1.0)) * cosine
    factors = []
    for kernel in (cosine, lobe):
        lit = kernel @ light
        shadowed = (kernel * visibility) @ light
        factors.append(torch.where(lit > 1e-12, shadowed / lit.clamp_min(1e-12), torch.ones_like(lit)))
    return torch.cat(factors, dim=-1).clamp(0.0, 1.0)


def inputs(n: int, rows: int, seed: int = 0, dtype=torch.float32):
    """Random Gaussians: visibility partly 0, partly 1, partly between (the object's shadows), normals of either sign,
    roughness over its whole range (also 1, and kappa's cap), the sky's light cells."""
    g = torch.Generator().manual_seed(seed)
    d = 2 * rows * rows
    visibility = torch.rand(n, d, generator=g) * (torch.rand(n, d, generator=g) > 0.3)
    visibility[torch.rand(n, d, generator=g) > 0.7] = 1.0
    normals = F.normalize(torch.randn(n, 3, generator=g), dim=-1)
    view_dirs = F.normalize(normals + 0.8 * torch.randn(n, 3, generator=g), dim=-1)
    roughness = torch.rand(n, generator=g)
    roughness[:3] = torch.tensor([1.0, 0.02, 0.3])
    cells = downsample_latlong(sky_map(4 * rows), rows)
    return [x.to(dtype) for x in (visibility, normals, view_dirs, roughness, cells)]


def values_and_gradients(function, visibility, normals, view_dirs, roughness, cells, weights, grads=(1, 3, 4)):
    leaves = [visibility, normals, view_dirs, roughness, cells]
    for i in grads:
        leaves[i] = leaves[i].clone().requires_grad_()
    out = function(*leaves)
    (out * weights).sum().backward()
    return out.detach(), [leaves[i].grad for i in grads]


@pytest.mark.parametrize("rows", [4, 8])
def test_factors_and_their_gradients_equal_the_formula_op_by_op(rows):
    visibility, normals, view_dirs, roughness, cells = inputs(300, rows)
    weights = torch.rand(300, 6, generator=torch.Generator().manual_seed(5))
    expected, expected_grads = values_and_gradients(
        reference_shadow_factors, visibility, normals, view_dirs, roughness, cells, weights
    )
    found, grads = values_and_gradients(shadow_factors, visibility, normals, view_dirs, roughness, cells, weights)
    assert 0.05 < float(expected.mean()) < 0.95  # shadowed, not all lit or all dark
    torch.testing.assert_close(found, expected, atol=1e-6, rtol=1e-5)
    for name, got, want in zip(("normals", "roughness", "light"), grads, expected_grads):
        assert float(want.abs().max()) > 0, name
        torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-4, msg=name)


def test_the_light_alone_takes_gradients_as_in_the_light_warm_up():
    """Materials and normals fixed (the warm-up): only the light's gradient, the same as the formula's."""
    visibility, normals, view_dirs, roughness, cells = inputs(200, 4, seed=3)
    weights = torch.rand(200, 6, generator=torch.Generator().manual_seed(6))
    _, (expected,) = values_and_gradients(
        reference_shadow_factors, visibility, normals, view_dirs, roughness, cells, weights, grads=(4,)
    )
    _, (found,) = values_and_gradients(shadow_factors, visibility, normals, view_dirs, roughness, cells, weights, (4,))
    torch.testing.assert_close(found, expected, atol=1e-5, rtol=1e-4)


def test_gradcheck_of_the_shadow_factors():
    visibility, normals, view_dirs, roughness, cells = inputs(6, 2, seed=1, dtype=torch.float64)
    visibility = visibility.clamp(0.05, 0.95)  # inside (0, 1): no factor at the clamp's edge
    roughness = roughness.clamp(0.2, 0.9)  # away from kappa's cap, where the gradient steps
    normals.requires_grad_()
    roughness.requires_grad_()
    cells.requires_grad_()

    def factors(n, r, c):
        return shadow_factors(visibility, n, view_dirs, r, c)

    assert torch.autograd.gradcheck(factors, (normals, roughness, cells), eps=1e-6, atol=1e-6)
