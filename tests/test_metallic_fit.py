"""The metallic fit (`matspray.method.refine.metallic`): against a brute-force linear program, on a blurred edge, and in
refinement (metallic only)."""

from dataclasses import replace

import pytest
import torch

from matspray.errors import SettingError
from matspray.material import METALLIC_INDEX
from matspray.method.refine.loop import RefineConfig, refine
from matspray.method.refine.metallic import MetallicFitConfig, fit_loss, fit_metallic
from tests.test_refine import lifted_scene, refine_inputs  # noqa: F401 (the fixture)


def dense_render(matrices: list[torch.Tensor], shape: tuple[int, int]):
    """A FrozenViews.render stand-in: view v blends features [N, C] by `matrices[v]` [H * W, N] into [H, W, C]."""

    def render(index: int, features: torch.Tensor):
        matrix = matrices[index].to(features)
        blended = (matrix @ features).reshape(*shape, -1)
        return blended, matrix.sum(1).reshape(shape)

    return render


def blocks_of(start, matrices, targets, pull, photo_target=None, photo_weight=0.0):
    """The fit's objective averaged over the views (what its fixed cycle of one view per step minimises) as blocks
    (A [R, N], t [R], weight) of sum_b weight_b * mean_r |A_b m - t_b|: each view's normalised blend, the pull, and
    the L1 stand-in for the photo term (`photo_target`, every view the same)."""
    n, views = len(start), len(matrices)
    blocks = [(m / m.sum(1, keepdim=True), t.reshape(-1), 1.0 / views) for m, t in zip(matrices, targets)]
    blocks.append((torch.eye(n), start, pull))
    if photo_target is not None:
        blocks.append((torch.eye(n), photo_target, photo_weight))
    return blocks


def objective(values, blocks) -> float:
    return sum(weight * float((a @ values - t).abs().mean()) for a, t, weight in blocks)


def linear_program_optimum(blocks, n: int):
    """The exact minimiser over m in [0, 1]^n of `objective` by scipy's LP solver (variables m, then each block
    row's positive and negative residual parts)."""
    scipy_optimize = pytest.importorskip("scipy.optimize")
    import numpy as np

    rows = sum(len(t) for _, t, _ in blocks)
    equality, rhs, cost = np.zeros((rows, n + 2 * rows)), [], [0.0] * n
    row = 0
    for a, t, weight in blocks:
        for r in range(len(t)):
            equality[row, :n] = a[r].double().numpy()
            equality[row, n + 2 * row] = -1.0  # A m - t = positive part - negative part
            equality[row, n + 2 * row + 1] = 1.0
            rhs.append(float(t[r]))
            cost += [weight / len(t)] * 2
            row += 1
    bounds = [(0.0, 1.0)] * n + [(0.0, None)] * (2 * rows)
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
    config = MetallicFitConfig(steps=6000, pull=0.3, lr=0.002)
    fitted = fit_metallic(start, dense_render(matrices, (3, 3)), targets, [torch.ones(3, 3)] * len(targets), config)
    blocks = blocks_of(start, matrices, targets, config.pull)
    exact, best = linear_program_optimum(blocks, len(start))
    assert abs(best - objective(exact, blocks)) < 1e-6  # the LP models the objective
    # and so does fit_loss: the objective of one view's image and the pull, at any values
    ones = torch.ones(3, 3)
    one_view = fit_loss(exact, start, *dense_render(matrices, (3, 3))(0, exact[:, None]), targets[0], ones, 0.3)
    assert abs(float(one_view) - objective(exact, [blocks[0][:2] + (1.0,), blocks[-1]])) < 1e-5
    assert objective(fitted, blocks) <= best + 5e-3, (objective(fitted, blocks), best)
    assert float((fitted - exact).abs().max()) < 0.05, (fitted, exact)


def test_the_photo_term_is_weighed_in_as_the_linear_program_says():
    start, matrices, targets = random_problem(3)
    wanted = torch.linspace(0.9, 0.1, len(start))  # what a stand-in photo term, L1 so the LP stays exact, asks for
    config = MetallicFitConfig(steps=6000, pull=0.1, lr=0.002, photo_weight=0.7)
    fitted = fit_metallic(
        start,
        dense_render(matrices, (3, 3)),
        targets,
        [torch.ones(3, 3)] * len(targets),
        config,
        photo=lambda index, values: (values - wanted).abs().mean(),
    )
    blocks = blocks_of(start, matrices, targets, config.pull, wanted, config.photo_weight)
    exact, best = linear_program_optimum(blocks, len(start))
    assert objective(fitted, blocks) <= best + 5e-3, (objective(fitted, blocks), best)
    assert float((fitted - exact).abs().max()) < 0.05, (fitted, exact)
    maps_alone, _ = linear_program_optimum(blocks[:-1], len(start))
    assert float((maps_alone - exact).abs().max()) > 0.1  # the photo term changed the answer


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
    for bad in ({"steps": -1}, {"pull": -0.1}, {"lr": -1.0}, {"photo_weight": -1.0}):
        with pytest.raises(SettingError):
            MetallicFitConfig(**bad)


def test_refinement_fits_only_the_metallic(lifted_scene):  # noqa: F811 (the fixture)
    gaussians, normals, _, views, maps, lifted = lifted_scene
    inputs = refine_inputs(gaussians, normals, lifted, views, maps)
    plain = RefineConfig(iterations=4, envmap_height=8, light_warmup=0)
    fit = MetallicFitConfig(steps=40, pull=0.0, lr=0.05, photo_weight=5.0)
    fitted = replace(plain, metallic_fit=fit)
    maps_alone = replace(plain, metallic_fit=replace(fit, photo_weight=0.0))
    before, after, without_photos = (refine(inputs, c, progress=False) for c in (plain, fitted, maps_alone))
    others = [i for i in range(5) if i != METALLIC_INDEX]
    assert torch.equal(before.materials[:, others], after.materials[:, others])
    assert torch.equal(before.normals, after.normals)
    moved = (after.materials[:, METALLIC_INDEX] - before.materials[:, METALLIC_INDEX]).abs()
    assert float(moved.max()) > 0.05
    metallic = after.materials[:, METALLIC_INDEX]
    assert 0.0 <= float(metallic.min()) <= float(metallic.max()) <= 1.0

    # the fit lowers its own image term, summed over the views, against the merger's metallic
    def image_error(materials):
        from matspray.method.refine.loop import TrainingViews

        training = TrainingViews(inputs)
        total = 0.0
        for index in range(len(views)):
            blended, alpha = training.frozen.render(index, materials[:, METALLIC_INDEX : METALLIC_INDEX + 1])
            surface = training.constants(index).surface
            total += float(fit_loss(materials[:, 0], materials[:, 0], blended, alpha, maps[index][..., 4], surface, 0))
        return total

    assert image_error(after.materials) < image_error(before.materials)
    # `full` has a light, so the photos have their say: the maps alone fit closer to the maps
    assert not torch.equal(after.materials, without_photos.materials)
    assert image_error(without_photos.materials) < image_error(after.materials)
