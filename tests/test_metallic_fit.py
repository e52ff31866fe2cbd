"""The metallic fit (`matspray.metallic_fit`): against a brute-force linear program, on a blurred edge, and in
refinement (metallic only)."""

import pytest
import torch

from matspray.errors import SettingError
from matspray.material import METALLIC_INDEX
from matspray.metallic_fit import MetallicFitConfig, fit_loss, fit_metallic
from matspray.refine import RefineConfig, refine
from tests.test_refine import lifted_scene, refine_inputs  # noqa: F401 (the fixture)


def dense_render(matrices: list[torch.Tensor], shape: tuple[int, int]):
    """A FrozenViews.render stand-in: view v blends features [N, C] by `matrices[v]` [H * W, N] into [H, W, C]."""

    def render(index: int, features: torch.Tensor):
        matrix = matrices[index].to(features)
        blended = (matrix @ features).reshape(*shape, -1)
        return blended, matrix.sum(1).reshape(shape)

    return render


def objective(values, start, matrices, targets, pull) -> float:
    """The fit's objective averaged over the views: what its fixed cycle of one view per step minimises."""
    render = dense_render(matrices, tuple(targets[0].shape))
    ones = torch.ones_like(targets[0])
    terms = [fit_loss(values, start, *render(v, values[:, None]), targets[v], ones, pull) for v in range(len(targets))]
    return float(sum(terms)) / len(terms)


def linear_program_optimum(start, matrices, targets, pull):
    """The exact minimiser of `objective` over m in [0, 1]^N by scipy's LP solver (variables m, then per pixel and
    per Gaussian the positive and negative parts of the residuals)."""
    scipy_optimize = pytest.importorskip("scipy.optimize")
    import numpy as np

    n = len(start)
    views = len(matrices)
    pixels = targets[0].numel()
    rhs = []
    cost = [0.0] * n
    blocks = []
    for matrix, target in zip(matrices, targets):
        coverage = matrix.sum(1, keepdim=True)
        blocks.append(((matrix / coverage).double().numpy(), target.reshape(-1).double().numpy()))
    count = n + 2 * views * pixels + 2 * n
    equality = np.zeros((views * pixels + n, count))
    for v, (normalised, target) in enumerate(blocks):
        for p in range(pixels):
            row = v * pixels + p
            equality[row, :n] = normalised[p]
            equality[row, n + 2 * row] = -1.0  # r+ : residual = r+ - r-
            equality[row, n + 2 * row + 1] = 1.0
            rhs.append(target[p])
    for i in range(n):
        row = views * pixels + i
        equality[row, i] = 1.0
        equality[row, n + 2 * views * pixels + 2 * i] = -1.0
        equality[row, n + 2 * views * pixels + 2 * i + 1] = 1.0
        rhs.append(float(start[i]))
    cost += [1.0 / (views * pixels)] * (2 * views * pixels) + [pull / n] * (2 * n)
    bounds = [(0.0, 1.0)] * n + [(0.0, None)] * (count - n)
    solution = scipy_optimize.linprog(cost, A_eq=equality, b_eq=rhs, bounds=bounds, method="highs")
    assert solution.status == 0, solution.message
    return torch.tensor(solution.x[:n], dtype=torch.float32), float(solution.fun)


def random_problem(seed: int, n: int = 5, side: int = 3, views: int = 2):
    generator = torch.Generator().manual_seed(seed)
    matrices = [torch.rand(side * side, n, generator=generator) ** 3 for _ in range(views)]  # uneven blends
    matrices = [m / m.sum(1, keepdim=True) * 0.9 for m in matrices]  # coverage 0.9 everywhere
    targets = [torch.rand(side, side, generator=generator).round() for _ in range(views)]  # a near-binary map
    start = torch.rand(n, generator=generator)
    return start, matrices, targets


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_fit_reaches_the_linear_programs_optimum(seed):
    start, matrices, targets = random_problem(seed)
    pull = 0.3
    config = MetallicFitConfig(steps=6000, pull=pull, lr=0.002)
    fitted = fit_metallic(start, dense_render(matrices, (3, 3)), targets, [torch.ones(3, 3)] * len(targets), config)
    exact, best = linear_program_optimum(start, matrices, targets, pull)
    reached = objective(fitted, start, matrices, targets, pull)
    assert abs(best - objective(exact, start, matrices, targets, pull)) < 1e-6  # the LP models the objective
    assert reached <= best + 5e-3, (reached, best)
    assert float((fitted - exact).abs().max()) < 0.05, (fitted, exact)


def blurred_edge(count: int = 12):
    """A row of Gaussians over a metal edge at its middle, each pixel blending a Gaussian with its two neighbours
    (weights 0.25 / 0.5 / 0.25 of coverage 1), and the lift's blurred values: each Gaussian the map's value around
    it, smoothed."""
    matrix = torch.zeros(count, count)
    for p in range(count):
        for offset, weight in ((-1, 0.25), (0, 0.5), (1, 0.25)):
            matrix[p, min(max(p + offset, 0), count - 1)] += weight
    truth = (torch.arange(count) >= count // 2).float()
    blurred = (matrix @ truth).clamp(0, 1)
    return matrix, truth, blurred


def test_the_fit_sharpens_a_blurred_edge_and_the_pull_holds_it():
    matrix, truth, blurred = blurred_edge()
    render_row = dense_render([matrix], (1, len(truth)))  # a 1 x count image
    target, surface = truth[None], torch.ones(1, len(truth))

    def error(values):
        blended, alpha = render_row(0, values[:, None])
        return float((blended[..., 0] / alpha - target).abs().mean())

    sharpened = fit_metallic(blurred, render_row, [target], [surface], MetallicFitConfig(steps=800, pull=0.05))
    held = fit_metallic(blurred, render_row, [target], [surface], MetallicFitConfig(steps=800, pull=50.0))
    off = fit_metallic(blurred, render_row, [target], [surface], MetallicFitConfig(steps=0))
    # the best any values in [0, 1] can do is the truth's own values (the blend still smears its edge pixel pair)
    assert error(sharpened) < error(truth) + 1e-3 < error(blurred) - 0.015
    assert float((sharpened - truth).abs().max()) < 0.05  # the edge's Gaussians are the truth's again
    assert float((held - blurred).abs().max()) < 0.02  # a strong pull keeps the start
    assert torch.equal(off, blurred)


def test_settings_are_checked():
    for bad in ({"steps": -1}, {"pull": -0.1}, {"lr": -1.0}):
        with pytest.raises(SettingError):
            MetallicFitConfig(**bad)


def test_refinement_fits_only_the_metallic(lifted_scene):  # noqa: F811 (the fixture)
    gaussians, normals, _, views, maps, lifted = lifted_scene
    inputs = refine_inputs(gaussians, normals, lifted, views, maps)
    plain = RefineConfig(iterations=4, envmap_height=8, light_warmup=0)
    fitted = RefineConfig(
        iterations=4, envmap_height=8, light_warmup=0, metallic_fit=MetallicFitConfig(steps=40, pull=0.0, lr=0.05)
    )
    before, after = (refine(inputs, c, progress=False) for c in (plain, fitted))
    others = [i for i in range(5) if i != METALLIC_INDEX]
    assert torch.equal(before.materials[:, others], after.materials[:, others])
    assert torch.equal(before.normals, after.normals)
    moved = (after.materials[:, METALLIC_INDEX] - before.materials[:, METALLIC_INDEX]).abs()
    assert float(moved.max()) > 0.05
    metallic = after.materials[:, METALLIC_INDEX]
    assert 0.0 <= float(metallic.min()) <= float(metallic.max()) <= 1.0

    # the fit lowers its own image term, summed over the views, against the merger's metallic
    def image_error(materials):
        from matspray.refine import TrainingViews

        training = TrainingViews(inputs)
        total = 0.0
        for index in range(len(views)):
            blended, alpha = training.frozen.render(index, materials[:, METALLIC_INDEX : METALLIC_INDEX + 1])
            surface = training.constants(index).surface
            total += float(fit_loss(materials[:, 0], materials[:, 0], blended, alpha, maps[index][..., 4], surface, 0))
        return total

    assert image_error(after.materials) < image_error(before.materials)
