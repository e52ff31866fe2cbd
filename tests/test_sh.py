"""Spherical-harmonics colour: the basis against scipy's complex harmonics, orthonormality, colour helpers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.special import sph_harm_y

from matspray.render.shade.latlong import pixel_directions, pixel_solid_angles
from matspray.render.shade.sh import rgb_to_sh_dc, sh_basis, sh_dc_to_rgb, sh_to_rgb


def random_directions(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)


def test_basis_is_real_form_of_scipy_harmonics():
    """3DGS's basis k = l^2 + l + m is sqrt(2) Im Y_l^|m| (m < 0), Y_l^0, sqrt(2) Re Y_l^m (m > 0) of the
    complex harmonics with the Condon-Shortley phase (scipy's)."""
    dirs = random_directions(50)
    polar = torch.acos(dirs[:, 2]).numpy()
    azimuth = torch.atan2(dirs[:, 1], dirs[:, 0]).numpy()
    ours = sh_basis(dirs, 3).numpy()
    for band in range(4):
        for m in range(-band, band + 1):
            y = sph_harm_y(band, abs(m), polar, azimuth)
            expected = y.real if m == 0 else math.sqrt(2) * (y.imag if m < 0 else y.real)
            np.testing.assert_allclose(ours[:, band * band + band + m], expected, atol=1e-12, err_msg=f"l={band} m={m}")


def test_basis_is_orthonormal_on_the_sphere():
    dirs = pixel_directions(128, 256, dtype=torch.float64).reshape(-1, 3)
    weights = pixel_solid_angles(128, 256, dtype=torch.float64).reshape(-1)
    basis = sh_basis(dirs, 3)  # [P, 16]
    gram = basis.T @ (basis * weights[:, None])
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=2e-3, rtol=0)


def test_band_energy_is_rotation_invariant():
    """Unsold's theorem: sum_m Y_lm(d)^2 = (2l + 1) / (4 pi) for every direction."""
    basis = sh_basis(random_directions(100, 1), 3)
    for band in range(4):
        energy = basis[:, band * band : (band + 1) ** 2].square().sum(-1)
        torch.testing.assert_close(energy, torch.full_like(energy, (2 * band + 1) / (4 * math.pi)))


def test_colour_helpers():
    rgb = torch.tensor([[0.1, 0.5, 0.9], [1.0, 0.0, 0.3]])
    torch.testing.assert_close(sh_dc_to_rgb(rgb_to_sh_dc(rgb)), rgb)
    sh = torch.zeros(2, 16, 3)
    sh[:, 0] = rgb_to_sh_dc(rgb)
    torch.testing.assert_close(sh_to_rgb(sh, random_directions(2).float()), rgb)  # DC only: view-independent
    sh[:, 1:] = torch.randn(2, 15, 3)
    dirs = random_directions(2, 3).float()
    torch.testing.assert_close(sh_to_rgb(sh, dirs, degree=0), rgb)  # higher bands ignored at degree 0
    one_band = sh_to_rgb(sh[:, :4], dirs)
    torch.testing.assert_close(sh_to_rgb(sh, dirs, degree=1), one_band)
    sh[:, 0] = -10.0
    assert (sh_to_rgb(sh, dirs) >= 0).all()


def test_rejects_bad_degrees():
    with pytest.raises(ValueError, match="degree must be"):
        sh_basis(random_directions(2), 4)
    with pytest.raises(ValueError, match="needs 16 coefficients"):
        sh_to_rgb(torch.zeros(2, 4, 3), random_directions(2).float(), degree=3)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_compiled_sh_colour_matches_torch_and_has_its_gradients(degree):
    from matspray.render.numba.sh import CompiledSH

    g = torch.Generator().manual_seed(degree)
    sh = (0.5 * torch.randn(40, 16, 3, generator=g, dtype=torch.float64)).requires_grad_()
    sh.data[:5, 0] = -3.0  # some colours clamped at 0
    means = torch.randn(40, 3, generator=g, dtype=torch.float64).requires_grad_()
    centre = torch.tensor([0.3, -4.0, 0.8], dtype=torch.float64)
    expected = sh_to_rgb(sh, torch.nn.functional.normalize(means - centre, dim=-1), degree)
    assert (expected == 0).any()
    torch.testing.assert_close(CompiledSH.apply(sh, means, centre, degree), expected, atol=1e-12, rtol=0)
    assert torch.autograd.gradcheck(lambda s, m: CompiledSH.apply(s, m, centre, degree), (sh, means))


def test_sh_colors_renders_with_the_compiled_loops_within_a_numba_block(monkeypatch):
    from matspray.data.camera import Camera
    from matspray.gaussians import Gaussians
    from matspray.render.backend import rendering_with
    from matspray.render.numba import sh as numba_sh
    from matspray.render.shade.sh import sh_colors

    g = torch.Generator().manual_seed(4)
    gaussians = Gaussians(
        torch.randn(30, 3, generator=g), torch.zeros(30, 3), torch.randn(30, 4), torch.zeros(30),
        torch.randn(30, 16, 3, generator=g),
    )  # fmt: skip
    camera = Camera.look_at([0.0, -4.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.7, 16, 16)
    calls = []
    original = numba_sh.CompiledSH.apply
    monkeypatch.setattr(numba_sh.CompiledSH, "apply", lambda *a: calls.append(a[-1]) or original(*a))
    expected = sh_colors(gaussians, camera, 2)
    assert calls == []
    with rendering_with("numba"):
        torch.testing.assert_close(sh_colors(gaussians, camera, 2), expected, atol=1e-6, rtol=1e-6)
    assert calls == [2]
