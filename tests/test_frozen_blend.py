"""Frozen views without their transposes on the CPU: the blend's backward pass as a compiled scatter through the one
matrix kept (matspray.render.numba.sparse) against the product with the transpose that was kept before, and what the
views keep."""

import pytest
import torch

from matspray.render.numba import sparse
from matspray.render.raster.gbuffer import FrozenViews, SparseBlend, blend_matrix, frozen_views_bytes, hits_of_view
from tests.test_rasterize import random_scene


def random_hits(seed: int, hits: int, pixels: int, count: int, dtype, twice: bool = True):  # -> ids, ids, weights [M]
    """Random (Gaussian, pixel) weights, rows and columns left empty; `twice`: some pairs twice (a matrix sums them),
    else each pair once (as a view's hits)."""
    g = torch.Generator().manual_seed(seed)
    # the last two Gaussians in no pixel, the odd pixels see nothing
    if twice:
        gaussian_ids = torch.randint(0, count - 2, (hits,), generator=g)
        pixel_ids = torch.randint(0, pixels // 2, (hits,), generator=g) * 2
    else:
        pairs = torch.randperm((count - 2) * (pixels // 2), generator=g)[:hits]
        gaussian_ids, pixel_ids = pairs % (count - 2), pairs // (count - 2) * 2
    return gaussian_ids, pixel_ids, torch.rand(hits, generator=g, dtype=dtype)


def blend_both_ways(hits, pixels: int, count: int, channels: int, dtype, seed: int = 0):
    """The image and the features' gradient by the two-matrix path and by the matrix alone, and a float64 dense
    reference: (image, grad) x 3."""
    g = torch.Generator().manual_seed(seed + 1)
    features = torch.rand(count, channels, generator=g, dtype=dtype)
    upstream = torch.rand(pixels, channels, generator=g, dtype=dtype)
    matrix = blend_matrix(hits[0], hits[1], hits[2], pixels, count)  # [P, N]
    transposed = blend_matrix(hits[1], hits[0], hits[2], count, pixels)  # [N, P]
    results = []
    for kept in (transposed, None):
        leaf = features.clone().requires_grad_(True)
        image = SparseBlend.apply(leaf, matrix, kept)
        (grad,) = torch.autograd.grad(image, leaf, upstream)
        results.append((image.detach(), grad))
    dense = torch.zeros(pixels, count, dtype=torch.float64).index_put_(
        (hits[1], hits[0]), hits[2].double(), accumulate=True
    )
    results.append((dense @ features.double(), dense.T @ upstream.double()))
    return results


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("channels", [1, 3, 8, 14])
def test_backward_without_the_transpose_is_the_product_with_it(channels, dtype, monkeypatch):
    """Several chunks (CHUNK_HITS made small), so that the chunks' buffers and their sum are exercised."""
    monkeypatch.setattr(sparse, "CHUNK_HITS", 500)
    pixels, count = 40 * 30, 90
    hits = random_hits(channels, 3000, pixels, count, dtype)
    assert sparse.chunk_count(3000) == 6
    (old_image, old_grad), (image, grad), (dense_image, dense_grad) = blend_both_ways(
        hits, pixels, count, channels, dtype
    )
    assert torch.equal(image, old_image)  # the same forward product
    tolerance = dict(rtol=1e-5, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(grad, old_grad, **tolerance)
    torch.testing.assert_close(grad.double(), dense_grad, **tolerance)
    torch.testing.assert_close(image.double(), dense_image, **tolerance)
    assert grad.dtype == dtype and grad.shape == (count, channels)
    assert (grad[-2:] == 0).all() and (grad[:-2].abs().sum(-1) > 0).all()  # Gaussians in no pixel get nothing


def test_one_chunk_sums_in_the_transposes_order():
    """In one chunk each Gaussian's gradient is summed pixel by pixel, as the product with the transpose sums it:
    the same bits (where each pair is there once, as in a view)."""
    pixels, count = 24 * 20, 50
    hits = random_hits(7, 2000, pixels, count, torch.float32, twice=False)
    assert sparse.chunk_count(2000) == 1
    (_, old_grad), (_, grad), _ = blend_both_ways(hits, pixels, count, 5, torch.float32)
    assert torch.equal(grad, old_grad)


def test_the_gradient_has_the_same_bits_whatever_the_thread_count(monkeypatch):
    monkeypatch.setattr(sparse, "CHUNK_HITS", 300)
    pixels, count = 30 * 30, 70
    hits = random_hits(3, 4000, pixels, count, torch.float32)
    threads = torch.get_num_threads()
    grads = []
    try:
        for number in (1, 2, 3):
            torch.set_num_threads(number)  # numba takes as many threads as torch (at most its pool)
            grads.append(blend_both_ways(hits, pixels, count, 8, torch.float32)[1][1])
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(grads[0], grads[1]) and torch.equal(grads[0], grads[2])


def test_empty_matrices():
    """No weight at all: a view whose pixels see no Gaussian, also in several chunks' worth of rows."""
    hits = (torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long), torch.zeros(0))
    (_, old_grad), (image, grad), _ = blend_both_ways(hits, 16 * 12, 10, 3, torch.float32)
    assert (image == 0).all() and torch.equal(grad, torch.zeros(10, 3)) and torch.equal(old_grad, grad)


def test_gradcheck_without_the_transpose(monkeypatch):
    monkeypatch.setattr(sparse, "CHUNK_HITS", 40)
    pixels, count = 9 * 7, 12
    hits = random_hits(11, 150, pixels, count, torch.float64)
    matrix = blend_matrix(hits[0], hits[1], hits[2], pixels, count)
    features = torch.rand(count, 3, dtype=torch.float64, requires_grad=True)
    assert sparse.chunk_count(150) == 3
    assert torch.autograd.gradcheck(lambda f: SparseBlend.apply(f, matrix, None), (features,))


def frozen_scene(device: torch.device):
    gaussians, camera = random_scene(60, 4, width=32, height=24)[:2]
    return gaussians.to(device), camera.to(device)


def test_frozen_views_keep_the_transposes_only_for_cuda(device):
    """On the CPU one matrix per view (half the bytes of a matrix and its transpose); on CUDA (pytest --device cuda)
    both. The rendered image and the features' gradient are the two-matrix path's either way."""
    gaussians, camera = frozen_scene(device)
    frozen = FrozenViews(gaussians, [camera, camera], backend="torch")
    on_cuda = device.type == "cuda"
    assert [t is not None for t in frozen.transposed] == [on_cuda, on_cuda]
    pixels, count = 32 * 24, 60
    both = frozen_views_bytes(frozen.hits, pixels, count, 2, transposed=True)
    one = frozen_views_bytes(frozen.hits, pixels, count, 2, transposed=False)
    assert frozen.kept_bytes == (both if on_cuda else one) and frozen.describe()["bytes"] == frozen.kept_bytes
    assert frozen.describe()["transposed"] == on_cuda
    assert both - one == 8 * frozen.hits + 2 * 4 * (count + 1)  # the transposes' weights and row pointers
    features = torch.rand(count, 5, device=device, requires_grad=True)
    upstream = torch.rand(24, 32, 5, device=device)
    image, _ = frozen.render(1, features)
    (grad,) = torch.autograd.grad(image, features, upstream)
    gaussian_ids, pixel_ids, weights = hits_of_view(gaussians, camera, "torch")
    matrix = blend_matrix(gaussian_ids, pixel_ids, weights, pixels, count)
    transposed = blend_matrix(pixel_ids, gaussian_ids, weights, count, pixels)
    leaf = features.detach().clone().requires_grad_(True)
    old_image = SparseBlend.apply(leaf, matrix, transposed)
    (old_grad,) = torch.autograd.grad(old_image, leaf, upstream.reshape(pixels, 5))
    torch.testing.assert_close(image.reshape(pixels, 5), old_image, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(grad, old_grad, rtol=1e-5, atol=1e-5)
    assert grad.abs().sum() > 0
    kept = sum(p.numel() * p.element_size() for p in (matrix.crow_indices(), matrix.col_indices(), matrix.values()))
    assert frozen.kept_bytes == 2 * kept + (2 * 8 * len(weights) + 2 * 4 * (count + 1) if on_cuda else 0)


def test_a_view_that_sees_no_gaussian(device):
    gaussians, camera = frozen_scene(device)
    gaussians.means = camera.center + 2.0 * (camera.center - gaussians.means)  # all behind the camera
    frozen = FrozenViews(gaussians, [camera], backend="torch")
    assert frozen.hits == 0 and frozen.kept_bytes == frozen_views_bytes(0, 32 * 24, 60, 1, device.type == "cuda")
    features = torch.rand(60, 2, device=device, requires_grad=True)
    image, alpha = frozen.render(0, features)
    (grad,) = torch.autograd.grad(image.sum(), features)
    assert (image == 0).all() and (alpha == 0).all() and (grad == 0).all()
