"""G-buffers of views whose geometry is frozen: the blending weights are computed once per view, after
which rendering any per-Gaussian features is a sparse product (and so is its backward pass).

This is what makes material refinement cheap: the Gaussians do not move, only their materials do.

With backend gsplat nothing is kept per view: rendering the features again with the frozen Gaussians is one
kernel call, cheaper on a GPU than the sparse product and free of the matrices' memory. With backend torch
(and numba, whose frozen views are these same matrices, their weights computed by its compiled forward:
matspray.render.numba.weights) the
matrices stay where `storage` says: on the Gaussians' device, on the host (copied to the device view by view),
or "auto": on a CUDA device while it keeps DEVICE_RESERVE of its memory free, on the host after that
(`frozen_views_bytes` says how large they are). Frozen views of Gaussians on a CUDA device keep each matrix and its
transpose (the backward pass is cuSPARSE's product with the transpose); on the CPU only the matrix, packed in 4 bytes
a weight (16-bit columns and weights), its products compiled, the backward pass a scatter over it
(matspray.render.numba.sparse): a quarter of the memory (docs/dev/real-captures.md, "Frozen views without their
transposes" and "Packed frozen views").
"""

from __future__ import annotations

import warnings

import torch
from torch import Tensor

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians
from matspray.render.backend import active_backend
from matspray.render.raster.rasterize import rasterize, view_weights

# a (Gaussian, pixel) weight in one torch matrix: an int32 column index and a float32 value (int64 indices for a
# matrix of 2^31 entries or more: `blend_matrix`); kept twice on a CUDA device (the matrix and its transpose)
BYTES_PER_HIT = 4 + 4
DEVICE_RESERVE = 0.25  # share of a GPU's memory left free for the rest of refinement (storage "auto")


def frozen_views_bytes(hits: int, pixels: int, gaussians: int, views: int, transposed: bool = True) -> int:
    """Bytes the torch and numba backends' frozen views keep: `hits` (Gaussian, pixel) weights over all views, plus
    each view's row pointers (pixels + 1 int32). With `transposed` (frozen views on a CUDA device) torch's matrices
    and their transposes (the weights again, gaussians + 1 row pointers); without (on the CPU) the packed matrices
    (2 bytes a weight, and 2 a column index for up to 2^16 Gaussians, 4 beyond)."""
    if transposed:
        return 2 * BYTES_PER_HIT * hits + 4 * views * (pixels + gaussians + 2)
    from matspray.render.numba.sparse import bytes_per_weight

    return bytes_per_weight(gaussians) * hits + 4 * views * (pixels + 1)


def sorted_pairs(
    column_ids: Tensor, row_ids: Tensor, weights: Tensor, n_rows: int, n_columns: int
) -> tuple[Tensor, Tensor, Tensor]:  # -> crow [n_rows + 1] int64, columns [M], weights [M]
    """The pairs (row_ids, column_ids) [M] and their `weights` [M] in CSR order: by row, then column. Made by one sort
    of the pairs, not by COO's coalesce (three times faster and without its intermediates)."""
    row_ids = row_ids.long()
    order = torch.argsort(row_ids * n_columns + column_ids.long())
    crow = torch.zeros(n_rows + 1, dtype=torch.int64, device=weights.device)
    crow[1:] = torch.bincount(row_ids.index_select(0, order), minlength=n_rows).cumsum(0)
    return crow, column_ids.index_select(0, order), weights.index_select(0, order)


def blend_matrix(column_ids: Tensor, row_ids: Tensor, weights: Tensor, n_rows: int, n_columns: int) -> Tensor:
    """Sparse CSR matrix [n_rows, n_columns] with `weights` [M] at (row_ids, column_ids) [M]: a view's
    blending weights as [pixels, Gaussians] (or, swapped, its transpose). A pair given twice is summed by the product.
    The indices are 32-bit where they fit: a third less memory (a dense view of many Gaussians holds tens of hits per
    pixel) and a faster product on the CPU."""
    index = torch.int32 if max(n_rows, n_columns, len(weights)) < 2**31 else torch.int64
    crow, columns, values = sorted_pairs(column_ids, row_ids, weights, n_rows, n_columns)
    with warnings.catch_warnings():  # torch calls sparse CSR "beta"; only its matrix product is used here
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(
            crow.to(index), columns.to(index), values, (n_rows, n_columns), check_invariants=False
        )


class SparseBlend(torch.autograd.Function):
    """features [N, C] -> matrix @ features [P, C]; the backward pass multiplies by the stored transpose, or without
    one (None: frozen views on the CPU, whose matrices are packed) scatters through the matrix
    (`transposed_product`)."""

    @staticmethod
    def forward(ctx, features: Tensor, matrix, transposed: Tensor | None) -> Tensor:  # matrix: Tensor or PackedBlend
        ctx.matrix, ctx.transposed = matrix, transposed
        return matrix @ features

    @staticmethod
    def backward(ctx, grad: Tensor):
        if ctx.transposed is not None:
            return ctx.transposed @ grad, None, None
        from matspray.render.numba.sparse import transposed_product

        return transposed_product(ctx.matrix, grad), None, None


def view_blend(gaussians: Gaussians, camera: Camera, backend: str) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """A view's blend matrix [H W, N] as CSR pairs (`sorted_pairs`: row pointers [H W + 1], Gaussian ids [M],
    weights [M]), each Gaussian's coverage [N] (the sum of its weights: pixels' worth) and the Gaussians with a
    weight [K] (increasing). Compiled on backend numba (a view whose record of hits would be too large falls back to
    torch's `view_weights`), torch's otherwise."""
    if backend == "numba" and gaussians.means.device.type == "cpu":
        from matspray.render.numba.backend import numba_view_blend

        found = numba_view_blend(gaussians, camera)
        if found is not None:
            return found
    gaussian_ids, pixel_ids, weights = view_weights(gaussians, camera)  # [M] each
    n = len(gaussians)
    crow, columns, values = sorted_pairs(gaussian_ids, pixel_ids, weights, camera.height * camera.width, n)
    return crow, columns, values, *coverage_of_hits(gaussian_ids, weights, n)


def coverage_of_hits(gaussian_ids: Tensor, weights: Tensor, n: int) -> tuple[Tensor, Tensor]:  # [M], [M] ->
    """Each of the n Gaussians' coverage [N] (the sum of its weights) and the Gaussians with a hit [K] (increasing)."""
    coverage = torch.zeros(n, device=weights.device).index_add_(0, gaussian_ids.long(), weights.float())
    return coverage, torch.unique(gaussian_ids).long()


def view_matrices(
    gaussians: Gaussians, camera: Camera, backend: str, on_host: bool
) -> tuple[list, int, Tensor, Tensor]:
    """What frozen views keep of one view: its blend matrix [H W, N] and, for Gaussians on a CUDA device, its
    transpose [N, H W] (torch's, moved to the host when `on_host`), else the matrix packed (on the CPU already); the
    number of weights, each Gaussian's coverage [N] and the Gaussians with a weight [K] (`view_blend`)."""
    n, pixels = len(gaussians), camera.height * camera.width
    if gaussians.means.device.type != "cpu":
        gaussian_ids, pixel_ids, weights = view_weights(gaussians, camera)  # [M] each
        matrices = [
            blend_matrix(gaussian_ids, pixel_ids, weights, pixels, n),  # [HW, N]
            blend_matrix(pixel_ids, gaussian_ids, weights, n, pixels),  # [N, HW]
        ]
        matrices = [_to_host(m) for m in matrices] if on_host else matrices
        return matrices, len(weights), *coverage_of_hits(gaussian_ids, weights, n)
    from matspray.render.numba.sparse import pack_blend

    crow, columns, weights, coverage, visible = view_blend(gaussians, camera, backend)
    return [pack_blend(crow, columns, weights, n)], len(weights), coverage, visible  # [HW, N]


class FrozenViews:
    """Views of frozen Gaussians, rendered with the backend of the enclosing `rendering_with` block (or `backend`).
    `storage` (torch backend): "device" keeps the blend matrices beside the Gaussians, "host" in (pinned) host
    memory, "auto" on the device while it has room (see the module's docstring). The transposes are kept where the
    Gaussians are on a CUDA device (`transposed`: None each on the CPU)."""

    def __init__(self, gaussians: Gaussians, cameras: list[Camera], backend: str | None = None, storage: str = "auto"):
        if storage not in ("device", "host", "auto"):
            raise ValueError(f"FrozenViews: storage is device, host or auto, got {storage!r}")
        self.gaussians = gaussians = gaussians.detach()
        self.cameras = cameras
        self.means = gaussians.means
        self.backend = backend or active_backend()
        device, n = self.means.device, len(gaussians)
        self.keeps_transposes = device.type != "cpu"  # CUDA's product with the transpose, the CPU's scatter
        self.matrices, self.transposed, self.visible_ids, self.coverage, self.on_host = [], [], [], [], []
        self.kept_bytes, self.hits = 0, 0  # what the frozen views hold beyond the Gaussians; (Gaussian, pixel) weights
        for camera in cameras:
            if self.backend == "gsplat":
                coverage = rendered_weights(gaussians, camera, self.backend)  # [N]
                self.visible_ids.append(torch.nonzero(coverage > 0).squeeze(1))
                self.coverage.append(coverage)
                continue
            on_host = storage == "host" or (storage == "auto" and not _room_on(device))
            matrices, hits, coverage, visible = view_matrices(gaussians, camera, self.backend, on_host)
            self.on_host.append(on_host)
            self.hits += hits
            self.kept_bytes += sum(_sparse_bytes(m) for m in matrices)
            self.matrices.append(matrices[0])
            self.transposed.append(matrices[1] if self.keeps_transposes else None)
            self.visible_ids.append(visible)  # [K] Gaussians that contribute to the view
            self.coverage.append(coverage)  # [N] pixels' worth
        self.alphas = [self._blend(index, torch.ones(n, 1, device=device))[..., 0] for index in range(len(cameras))]
        self.centers = [camera.center.to(self.means) for camera in cameras]  # [3] each
        self._contributing: dict[tuple[int, float], Tensor] = {}  # (view, min_coverage) -> ids, asked every step

    def __len__(self) -> int:
        return len(self.cameras)

    def _blend(self, index: int, features: Tensor) -> Tensor:  # [N, C] -> [H, W, C]
        camera = self.cameras[index]
        if self.backend == "gsplat":
            return rasterize(self.gaussians, camera, features, backend=self.backend).features
        matrices = [self.matrices[index], self.transposed[index]]
        if self.keeps_transposes:  # torch's matrices (the packed ones' products take features of any float type)
            if self.on_host[index]:
                matrices = [m.to(features.device, non_blocking=True) for m in matrices]
            if features.dtype != matrices[0].dtype:  # e.g. float64 for gradcheck
                matrices = [m.to(features.dtype) for m in matrices]
        return SparseBlend.apply(features.contiguous(), *matrices).reshape(camera.height, camera.width, -1)

    def render(self, index: int, features: Tensor) -> tuple[Tensor, Tensor]:
        """features [N, C] -> blended features [H, W, C] over black, and the coverage alpha [H, W]."""
        return self._blend(index, features), self.alphas[index]

    def describe(self) -> dict:
        """What the views keep, for a stage record: the backend, bytes, (Gaussian, pixel) weights, whether the
        transposes are kept too or the matrices packed, pixels, views on the host."""
        return {
            "backend": self.backend,
            "bytes": self.kept_bytes,
            "transposed": self.keeps_transposes and self.backend != "gsplat",
            "packed": not self.keeps_transposes and self.backend != "gsplat",  # 16-bit weights and columns
            "hits": self.hits,
            "gaussians": len(self.means),
            "pixels": sum(c.width * c.height for c in self.cameras),
            "views": len(self.cameras),
            "views_on_host": sum(self.on_host),
        }

    def visible(self, index: int) -> Tensor:  # [N] bool: Gaussians that contribute to the view
        visible = torch.zeros(len(self.means), dtype=torch.bool, device=self.means.device)
        visible[self.visible_ids[index]] = True
        return visible

    def contributing_ids(self, index: int, min_coverage: float) -> Tensor:  # [K'] subset of visible_ids
        """The visible Gaussians whose blending weights in view `index` add up to >= `min_coverage` pixels (made once
        per view and threshold: selecting them waits for the device)."""
        key = (index, min_coverage)
        if key not in self._contributing:
            visible = self.visible_ids[index]
            self._contributing[key] = (
                visible[self.coverage[index][visible] >= min_coverage] if min_coverage > 0 else visible
            )
        return self._contributing[key]

    def orient_normals(self, index: int, normals: Tensor) -> Tensor:  # [N, 3] -> [N, 3] facing view `index`
        return orient_towards(normals, self.means, self.centers[index])


def rendered_weights(gaussians: Gaussians, camera: Camera, backend: str | None = None) -> Tensor:  # -> [N]
    """The blending weight each Gaussian gets over the image of `camera`, in pixels' worth: the gradient of the
    rendered image's sum with respect to a constant per-Gaussian feature (one forward and backward pass)."""
    ones = torch.ones(len(gaussians), 1, device=gaussians.means.device, requires_grad=True)
    with torch.enable_grad():
        out = rasterize(
            gaussians.detach(), camera, ones, background=torch.zeros(1, device=ones.device), backend=backend
        )
        (grad,) = torch.autograd.grad(out.features.sum(), ones)
    return grad[:, 0]


def _room_on(device: torch.device) -> bool:
    """Whether `device` still has DEVICE_RESERVE of its memory free (the host's memory always counts as room)."""
    if device.type != "cuda":
        return True
    free, total = torch.cuda.mem_get_info(device)
    return free >= DEVICE_RESERVE * total


def _to_host(matrix: Tensor) -> Tensor:
    host = matrix.cpu()
    return host.pin_memory() if torch.cuda.is_available() else host


def _sparse_bytes(matrix) -> int:
    if not isinstance(matrix, Tensor):  # packed
        return matrix.nbytes
    parts = (matrix.crow_indices(), matrix.col_indices(), matrix.values())
    return sum(p.numel() * p.element_size() for p in parts)


def orient_normals(normals: Tensor, means: Tensor, camera: Camera) -> Tensor:  # [N, 3], [N, 3] -> [N, 3]
    """Flip each normal to face the camera (Gaussian normals have no reliable sign)."""
    return orient_towards(normals, means, camera.center.to(means))


def orient_towards(normals: Tensor, means: Tensor, center: Tensor) -> Tensor:  # [N, 3], [N, 3], [3] -> [N, 3]
    """Flip each normal to face the point `center` (a camera's position)."""
    to_camera = center - means
    facing = torch.where((normals * to_camera).sum(-1, keepdim=True) >= 0, 1.0, -1.0)  # [N, 1]
    return normals * facing  # a product by +-1: exact, and one operation in the backward pass
