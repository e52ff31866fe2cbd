"""Frozen views on the CPU: each view's blend matrix packed (16-bit columns and weights), its product and the
backward pass as a compiled scatter through it (matspray.render.numba.sparse), against float64 dense products of the
same weights and against the torch matrix and its transpose that were kept before, and what the views keep."""

import numpy as np
import pytest
import torch

from matspray.render.numba import sparse
from matspray.render.raster.gbuffer import (
    FrozenViews,
    SparseBlend,
    blend_matrix,
    frozen_views_bytes,
    sorted_pairs,
)
from matspray.render.raster.rasterize import view_weights
from tests.test_rasterize import random_scene

HALF_STEP = 0.5 / sparse.WEIGHT_STEPS  # the largest error of a packed weight


def packed_blend_matrix(gaussian_ids, pixel_ids, weights, pixels: int, count: int) -> sparse.PackedBlend:
    """The packed matrix [pixels, count] of (Gaussian, pixel) weights given in any order (a pair twice: summed)."""
    return sparse.pack_blend(*sorted_pairs(gaussian_ids, pixel_ids, weights, pixels, count), count)


def random_hits(seed: int, hits: int, pixels: int, count: int, dtype, twice: bool = True):  # -> ids, ids, weights [M]
    """Random (Gaussian, pixel) weights in [0, 1], rows and columns left empty; `twice`: some pairs twice (a matrix
    sums them), else each pair once (as a view's hits)."""
    g = torch.Generator().manual_seed(seed)
    # the last two Gaussians in no pixel, the odd pixels see nothing
    if twice:
        gaussian_ids = torch.randint(0, count - 2, (hits,), generator=g)
        pixel_ids = torch.randint(0, pixels // 2, (hits,), generator=g) * 2
    else:
        pairs = torch.randperm((count - 2) * (pixels // 2), generator=g)[:hits]
        gaussian_ids, pixel_ids = pairs % (count - 2), pairs // (count - 2) * 2
    return gaussian_ids, pixel_ids, torch.rand(hits, generator=g, dtype=dtype)


def unpacked(packed: sparse.PackedBlend, dtype=torch.float32) -> torch.Tensor:  # [M]
    """The weights as the products of `dtype` features use them: each step times 1 / WEIGHT_STEPS in that type."""
    real = torch.empty(0, dtype=dtype).numpy().dtype.type
    return torch.from_numpy(packed.steps.astype(real) * real(1.0 / sparse.WEIGHT_STEPS))


def dense_of(packed: sparse.PackedBlend, dtype=torch.float32) -> torch.Tensor:  # -> [P, N] float64
    """The weights that the products of `dtype` features use."""
    rows = torch.repeat_interleave(torch.arange(packed.shape[0]), torch.from_numpy(np.diff(packed.crow)).long())
    columns = torch.from_numpy(packed.col.astype(np.int64))
    dense = torch.zeros(packed.shape, dtype=torch.float64)
    return dense.index_put_((rows, columns), unpacked(packed, dtype).double(), accumulate=True)


def blend(features, upstream, matrix, transposed=None):  # -> image [P, C], grad [N, C]
    leaf = features.clone().requires_grad_(True)
    image = SparseBlend.apply(leaf, matrix, transposed)
    (grad,) = torch.autograd.grad(image, leaf, upstream)
    return image.detach(), grad


def blend_three_ways(hits, pixels: int, count: int, channels: int, dtype, seed: int = 0):
    """The image and the features' gradient by the packed matrix, by the float64 dense product of its weights and by
    torch's matrix and transpose of the unpacked weights: (image, grad) x 3."""
    g = torch.Generator().manual_seed(seed + 1)
    features = torch.rand(count, channels, generator=g, dtype=dtype)
    upstream = torch.rand(pixels, channels, generator=g, dtype=dtype)
    packed = packed_blend_matrix(hits[0], hits[1], hits[2], pixels, count)  # [P, N]
    dense = dense_of(packed, dtype)
    matrix = blend_matrix(hits[0], hits[1], hits[2], pixels, count)
    transposed = blend_matrix(hits[1], hits[0], hits[2], count, pixels)
    return (
        blend(features, upstream, packed),
        (dense @ features.double(), dense.T @ upstream.double()),
        blend(features, upstream, matrix, transposed),
    )


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("channels", [1, 3, 8, 14])
def test_packed_products_are_the_dense_ones_of_their_weights(channels, dtype, monkeypatch):
    """Several chunks (CHUNK_HITS made small), so that the chunks' buffers and their sum are exercised."""
    monkeypatch.setattr(sparse, "CHUNK_HITS", 500)
    pixels, count = 40 * 30, 90
    hits = random_hits(channels, 3000, pixels, count, dtype)
    assert sparse.chunk_count(3000) == 6
    (image, grad), (dense_image, dense_grad), (torch_image, torch_grad) = blend_three_ways(
        hits, pixels, count, channels, dtype
    )
    tolerance = dict(rtol=1e-5, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(grad.double(), dense_grad, **tolerance)
    torch.testing.assert_close(image.double(), dense_image, **tolerance)
    assert image.dtype == grad.dtype == dtype and grad.shape == (count, channels) and image.shape == (pixels, channels)
    assert (grad[-2:] == 0).all() and (grad[:-2].abs().sum(-1) > 0).all()  # Gaussians in no pixel get nothing
    assert (image[1::2] == 0).all()  # pixels that see nothing
    # against the unpacked weights: each weight within half a step, so each sum within its count of half steps
    per_pixel = torch.bincount(hits[1], minlength=pixels).max()
    per_gaussian = torch.bincount(hits[0], minlength=count).max()
    torch.testing.assert_close(image, torch_image, rtol=0, atol=float(per_pixel * HALF_STEP) + 1e-5)
    torch.testing.assert_close(grad, torch_grad, rtol=0, atol=float(per_gaussian * HALF_STEP) + 1e-5)


def test_packing_keeps_each_weight_within_half_a_step_and_16_bit_columns_up_to_2_16_gaussians():
    pixels = 50
    for count, column in ((2**16, np.uint16), (2**16 + 1, np.int32)):
        gaussian_ids = torch.tensor([0, count - 1, 7, 3, 7])
        pixel_ids = torch.tensor([4, 4, 0, 49, 0])
        weights = torch.tensor([1.0, 0.0, 0.3, 1e-6, 0.123456789])
        packed = packed_blend_matrix(gaussian_ids, pixel_ids, weights, pixels, count)
        assert packed.col.dtype == column and packed.steps.dtype == np.uint16 and packed.crow.dtype == np.int32
        assert packed.shape == (pixels, count) and packed.nbytes == 4 * (pixels + 1) + 5 * (2 + column().itemsize)
        assert packed.col.tolist() == [7, 7, 0, count - 1, 3]  # by pixel, then Gaussian
        assert packed.crow.tolist()[:6] == [0, 2, 2, 2, 2, 4] and packed.crow[-1] == 5
        expected = torch.tensor([0.3, 0.123456789, 1.0, 0.0, 1e-6])
        assert (unpacked(packed) - expected).abs().max() <= HALF_STEP
        assert unpacked(packed)[2] == 1.0 and unpacked(packed)[3] == 0.0  # the ends exactly
    wide = packed_blend_matrix(gaussian_ids, pixel_ids, weights, pixels, count)
    features = torch.rand(count, 2)
    torch.testing.assert_close((wide @ features).double(), dense_of(wide) @ features.double())


def test_the_products_have_the_same_bits_whatever_the_thread_count(monkeypatch):
    monkeypatch.setattr(sparse, "CHUNK_HITS", 300)
    pixels, count = 30 * 30, 70
    hits = random_hits(3, 4000, pixels, count, torch.float32)
    threads = torch.get_num_threads()
    results = []
    try:
        for number in (1, 2, 3):
            torch.set_num_threads(number)  # numba takes as many threads as torch (at most its pool)
            results.append(blend_three_ways(hits, pixels, count, 8, torch.float32)[0])
    finally:
        torch.set_num_threads(threads)
    for image, grad in results[1:]:
        assert torch.equal(image, results[0][0]) and torch.equal(grad, results[0][1])


def test_empty_matrices():
    """No weight at all: a view whose pixels see no Gaussian, also in several chunks' worth of rows."""
    hits = (torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long), torch.zeros(0))
    (image, grad), _, (_, torch_grad) = blend_three_ways(hits, 16 * 12, 10, 3, torch.float32)
    assert (image == 0).all() and torch.equal(grad, torch.zeros(10, 3)) and torch.equal(torch_grad, grad)


def test_gradcheck_of_the_packed_blend(monkeypatch):
    monkeypatch.setattr(sparse, "CHUNK_HITS", 40)
    pixels, count = 9 * 7, 12
    hits = random_hits(11, 150, pixels, count, torch.float64)
    matrix = packed_blend_matrix(hits[0], hits[1], hits[2], pixels, count)
    features = torch.rand(count, 3, dtype=torch.float64, requires_grad=True)
    assert sparse.chunk_count(150) == 3
    assert torch.autograd.gradcheck(lambda f: SparseBlend.apply(f, matrix, None), (features,))


def frozen_scene(device: torch.device):
    gaussians, camera = random_scene(60, 4, width=32, height=24)[:2]
    return gaussians.to(device), camera.to(device)


def test_frozen_views_keep_the_transposes_only_for_cuda(device):
    """On the CPU one packed matrix per view (a quarter of the bytes of a torch matrix and its transpose); on CUDA
    (pytest --device cuda) both torch matrices. The rendered image and the features' gradient are the two-matrix
    path's either way (within the packed weights' steps on the CPU)."""
    gaussians, camera = frozen_scene(device)
    frozen = FrozenViews(gaussians, [camera, camera], backend="torch")
    on_cuda = device.type == "cuda"
    assert [t is not None for t in frozen.transposed] == [on_cuda, on_cuda]
    assert all(isinstance(m, torch.Tensor) == on_cuda for m in frozen.matrices)
    pixels, count = 32 * 24, 60
    both = frozen_views_bytes(frozen.hits, pixels, count, 2, transposed=True)
    one = frozen_views_bytes(frozen.hits, pixels, count, 2, transposed=False)
    assert frozen.kept_bytes == (both if on_cuda else one) and frozen.describe()["bytes"] == frozen.kept_bytes
    assert frozen.describe()["transposed"] == on_cuda and frozen.describe()["packed"] == (not on_cuda)
    assert both - one == 12 * frozen.hits + 2 * 4 * (count + 1)  # the transposes and 16-bit weights and columns
    features = torch.rand(count, 5, device=device, requires_grad=True)
    upstream = torch.rand(24, 32, 5, device=device)
    image, _ = frozen.render(1, features)
    (grad,) = torch.autograd.grad(image, features, upstream)
    gaussian_ids, pixel_ids, weights = view_weights(gaussians, camera)
    matrix = blend_matrix(gaussian_ids, pixel_ids, weights, pixels, count)
    transposed = blend_matrix(pixel_ids, gaussian_ids, weights, count, pixels)
    old_image, old_grad = blend(features.detach(), upstream.reshape(pixels, 5), matrix, transposed)
    steps = 0 if on_cuda else HALF_STEP * max(torch.bincount(pixel_ids).max(), torch.bincount(gaussian_ids).max())
    torch.testing.assert_close(image.reshape(pixels, 5), old_image, rtol=1e-6, atol=1e-6 + 5 * float(steps))
    torch.testing.assert_close(grad, old_grad, rtol=1e-5, atol=1e-5 + 30 * float(steps))
    assert grad.abs().sum() > 0
    if on_cuda:
        kept = sum(p.numel() * p.element_size() for p in (matrix.crow_indices(), matrix.col_indices(), weights))
        assert frozen.kept_bytes == 2 * kept + 2 * 8 * len(weights) + 2 * 4 * (count + 1)
    else:
        assert frozen.kept_bytes == 2 * (4 * (pixels + 1) + 4 * len(weights))


def test_a_view_that_sees_no_gaussian(device):
    gaussians, camera = frozen_scene(device)
    gaussians.means = camera.center + 2.0 * (camera.center - gaussians.means)  # all behind the camera
    frozen = FrozenViews(gaussians, [camera], backend="torch")
    assert frozen.hits == 0 and frozen.kept_bytes == frozen_views_bytes(0, 32 * 24, 60, 1, device.type == "cuda")
    features = torch.rand(60, 2, device=device, requires_grad=True)
    image, alpha = frozen.render(0, features)
    (grad,) = torch.autograd.grad(image.sum(), features)
    assert (image == 0).all() and (alpha == 0).all() and (grad == 0).all()
