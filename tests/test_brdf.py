"""The Cook-Torrance BRDF and the split-sum integration table against quadrature references."""

import math

import pytest
import torch

from matspray.render.shade.brdf import (
    cook_torrance,
    fresnel_schlick,
    ggx_ndf,
    reflect,
    smith_visibility,
    specular_f0,
)
from matspray.render.shade.brdf_lut import brdf_lut, hammersley, integrate_split_sum, lookup_brdf_lut
from matspray.render.shade.latlong import pixel_directions, pixel_solid_angles

f64 = torch.float64


def unit(*v):
    v = torch.tensor(v, dtype=f64)
    return v / v.norm()


def upper_hemisphere(height: int):
    """Directions [P, 3] and solid angles [P] of a fine lat-long grid, upper half only (z > 0)."""
    dirs = pixel_directions(2 * height, 4 * height, dtype=f64)[:height].reshape(-1, 3)
    weights = pixel_solid_angles(2 * height, 4 * height, dtype=f64)[:height].reshape(-1)
    return dirs, weights


def quadrature_rows(roughness: float) -> int:
    """Rows of the hemisphere grid for integrals over a lobe of this roughness to converge to ~1e-4
    (checked against 768 rows); a glossy lobe seen at grazing angles needs the finer grid."""
    return 384 if roughness < 0.25 else 192


def view_at(n_dot_v: float):
    return torch.tensor([math.sqrt(1 - n_dot_v**2), 0.0, n_dot_v], dtype=f64)


# ------------------------------------------------------------------------------------------ pieces
@pytest.mark.parametrize("roughness", [0.1, 0.3, 0.6, 1.0])
def test_ggx_ndf_projected_area_integrates_to_one(roughness):
    # integral of D(h) (n.h) over the hemisphere = 2 pi integral_0^{pi/2} D(cos t) cos t sin t dt = 1
    theta = torch.linspace(0, math.pi / 2, 200001, dtype=f64)
    alpha = torch.tensor(roughness**2, dtype=f64)
    integrand = ggx_ndf(torch.cos(theta), alpha) * torch.cos(theta) * torch.sin(theta)
    assert float(2 * math.pi * torch.trapezoid(integrand, theta)) == pytest.approx(1.0, abs=1e-6)


def test_smith_visibility_matches_lambda_form():
    # height-correlated G2 = 1 / (1 + Lambda(l) + Lambda(v)), Lambda(x) = (sqrt(1 + a^2 tan^2) - 1) / 2
    torch.manual_seed(0)
    nl, nv = torch.rand(2, 100, dtype=f64) * 0.98 + 0.02
    alpha = torch.rand(100, dtype=f64) * 0.9 + 0.05

    def lam(c):
        return (torch.sqrt(1 + alpha**2 * (1 - c**2) / c**2) - 1) / 2

    g2 = 1 / (1 + lam(nl) + lam(nv))
    torch.testing.assert_close(smith_visibility(nl, nv, alpha), g2 / (4 * nl * nv))


def test_fresnel_and_f0_limits():
    base = torch.tensor([[0.9, 0.5, 0.1]], dtype=f64)
    assert torch.allclose(specular_f0(base, torch.tensor([0.0], dtype=f64)), torch.full((1, 3), 0.04, dtype=f64))
    assert torch.allclose(specular_f0(base, torch.tensor([1.0], dtype=f64)), base)
    assert torch.allclose(fresnel_schlick(base, torch.tensor([1.0], dtype=f64)), base)  # head-on: F0
    assert torch.allclose(
        fresnel_schlick(base, torch.tensor([0.0], dtype=f64)), torch.ones(1, 3, dtype=f64)
    )  # grazing: 1


def test_reflect_mirrors_about_the_normal():
    n, d = unit(0.2, -0.3, 0.9), unit(0.5, 0.1, -0.4)
    r = reflect(d, n)
    assert float(r.norm()) == pytest.approx(1.0)
    assert float(r @ n) == pytest.approx(-float(d @ n))
    torch.testing.assert_close(r - d, (r - d) @ n * n)  # the change is along n only


# ------------------------------------------------------------------------------------------ the BRDF
def random_configuration(count: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    base = torch.rand(count, 3, generator=g, dtype=f64)
    rough = torch.rand(count, generator=g, dtype=f64) * 0.9 + 0.1
    metal = torch.rand(count, generator=g, dtype=f64)
    n = torch.nn.functional.normalize(torch.randn(count, 3, generator=g, dtype=f64), dim=-1)
    wo, wi = (
        torch.nn.functional.normalize(n + torch.randn(count, 3, generator=g, dtype=f64) * 0.6, dim=-1) for _ in range(2)
    )
    return base, rough, metal, n, wo, wi


def test_cook_torrance_is_reciprocal_and_zero_below_the_horizon():
    base, rough, metal, n, wo, wi = random_configuration(200)
    f = cook_torrance(base, rough, metal, n, wo, wi)
    assert (f > 0).sum() > 100  # most pairs lie above the surface
    torch.testing.assert_close(f, cook_torrance(base, rough, metal, n, wi, wo))
    below = reflect(wi, n)  # the mirror image of wi lies on the other side of the surface
    assert torch.all(cook_torrance(base, rough, metal, n, wo, below)[(wi * n).sum(-1) > 0] == 0)


def test_cook_torrance_lobes_by_hand():
    # head-on view and light: h = n, wo.h = 1 so F = F0, D = 1 / (pi a^2), V = 1 / 4
    n = unit(0, 0, 1)
    base, r, m = torch.tensor([0.7, 0.4, 0.2], dtype=f64), torch.tensor(0.5, dtype=f64), torch.tensor(0.3, dtype=f64)
    f = cook_torrance(base, r, m, n, n, n)
    f0 = 0.04 * (1 - m) + base * m
    expected = base * (1 - m) / math.pi + f0 / (math.pi * 0.0625) / 4
    torch.testing.assert_close(f, expected)


@pytest.mark.parametrize("roughness,n_dot_v", [(0.2, 0.1), (0.2, 1.0), (0.5, 0.5), (1.0, 0.1), (1.0, 1.0)])
def test_white_furnace(roughness, n_dot_v):
    # directional albedo integral f cos: a white metal (pure specular) loses energy but never gains it;
    # the Lambert lobe of a white dielectric returns exactly (1 - metallic) = 1 on top of its specular.
    dirs, dw = upper_hemisphere(quadrature_rows(roughness))
    n, wo = unit(0, 0, 1), view_at(n_dot_v)
    white = torch.ones(3, dtype=f64)

    def albedo(base_color, metallic):
        f = cook_torrance(
            base_color, torch.tensor(roughness, dtype=f64), torch.tensor(metallic, dtype=f64), n, wo, dirs
        )
        return (f[:, 0] * dirs[:, 2] * dw).sum()

    metal = float(albedo(white, 1.0))
    assert metal <= 1.0 + 1e-3
    # single-scattering GGX loses more energy the rougher it is (albedo ~0.31 at r = 1 head-on), but not all
    assert metal > {0.2: 0.9, 0.5: 0.8, 1.0: 0.25}[roughness]
    dielectric_specular = float(albedo(white * 0, 0.0))  # black base color: the F0 = 0.04 lobe alone
    assert dielectric_specular < (0.1 if n_dot_v >= 0.5 else 0.6)
    assert float(albedo(white, 0.0)) - dielectric_specular == pytest.approx(1.0, abs=2e-3)


def test_cook_torrance_gradcheck():
    base, rough, metal, n, wo, wi = random_configuration(6, seed=3)
    for x in (base, rough, metal, n):
        x.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda b, r, m, nn: cook_torrance(b, r, m, nn, wo, wi), (base, rough, metal, n))


# ------------------------------------------------------------------------------------------ the table
def test_hammersley_points():
    points = hammersley(8)
    assert points.shape == (8, 2)
    torch.testing.assert_close(points[:, 0], (torch.arange(8, dtype=f64) + 0.5) / 8)
    torch.testing.assert_close(points[:, 1], torch.tensor([0, 0.5, 0.25, 0.75, 0.125, 0.625, 0.375, 0.875], dtype=f64))


def split_sum_by_quadrature(n_dot_v: float, roughness: float):
    """A and B by brute force over the hemisphere, from the pure specular lobe (metallic 1, F0 = base color):
    F0 = 0 leaves B alone, F0 = 1 gives A + B."""
    dirs, dw = upper_hemisphere(quadrature_rows(roughness))
    n, wo = unit(0, 0, 1), view_at(n_dot_v)
    r = torch.tensor(roughness, dtype=f64)
    metal = torch.tensor(1.0, dtype=f64)  # pure specular lobe with F0 = base color

    def integral(f0):
        f = cook_torrance(torch.full((3,), f0, dtype=f64), r, metal, n, wo, dirs)
        return float((f[:, 0] * dirs[:, 2] * dw).sum())

    b = integral(0.0)
    return integral(1.0) - b, b


@pytest.mark.parametrize(
    "n_dot_v,roughness", [(0.1, 0.2), (0.15, 0.3), (0.5, 0.5), (0.8, 0.25), (0.95, 0.9), (0.3, 0.75)]
)
def test_lut_matches_quadrature(n_dot_v, roughness):
    a_ref, b_ref = split_sum_by_quadrature(n_dot_v, roughness)
    # the importance-sampled integrator itself, at the exact point
    a, b = integrate_split_sum(torch.tensor(n_dot_v, dtype=f64), torch.tensor(roughness, dtype=f64)).tolist()
    assert a == pytest.approx(a_ref, abs=2e-3) and b == pytest.approx(b_ref, abs=2e-3)
    # the bilinear lookup between texel centres (32 x 32) adds a little interpolation error
    a, b = lookup_brdf_lut(torch.tensor(n_dot_v, dtype=f64), torch.tensor(roughness, dtype=f64)).tolist()
    assert a == pytest.approx(a_ref, abs=5e-3) and b == pytest.approx(b_ref, abs=5e-3)


def test_lut_is_cached_and_bounded():
    assert brdf_lut(16, 64) is brdf_lut(16, 64)
    table = brdf_lut(dtype=torch.float64)
    assert table.shape == (32, 32, 2) and brdf_lut(dtype=torch.float32).dtype == torch.float32
    # A + B is the specular albedo of a white metal: in (0, 1], near 1 for smooth surfaces seen head-on
    assert torch.all(table >= 0) and torch.all(table.sum(-1) <= 1.0 + 1e-3)
    assert float(table[-1, 0].sum()) == pytest.approx(1.0, abs=5e-3)


def test_lut_lookup_is_differentiable():
    nv = torch.tensor([0.23, 0.61, 0.87], dtype=f64, requires_grad=True)
    r = torch.tensor([0.33, 0.52, 0.71], dtype=f64, requires_grad=True)
    assert torch.autograd.gradcheck(lookup_brdf_lut, (nv, r))
