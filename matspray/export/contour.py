"""The decimated mesh's silhouettes moved onto the asset's, vertex by vertex.

The level calibration (`silhouette.silhouette_offset`) moves the whole surface by one distance, so the mesh
covers as many pixels as the asset in total; locally its rim still strays by a fraction of a pixel either way,
which a metric that counts the silhouette charges in full against the asset, whose soft alpha sits on the truth
(docs/dev/export.md).

Each round, in every training view, the rim vertices (on an edge between a face turned to the camera and one
turned away) are moved along their normal by how far the asset's silhouette edge (alpha = min_alpha) lies from
the mesh's own (its coverage on a 4 x 4 sample grid per pixel), both found on the line through the vertex's
projection in the direction its normal projects to. Comparing the two edges on the same line, instead of the
vertex's own projection with the asset's edge, keeps out the bias of a rim vertex that sits a little inside the
mesh's outline (a fold of the faceted surface); a line that does not run cleanly from inside to outside for
both (a hidden rim, another part behind it) casts no vote, nor does a vertex whose normal points too nearly along
the ray to move its edge sideways.
"""

from __future__ import annotations

import numpy as np
import torch
import trimesh
from scipy.ndimage import binary_dilation
from scipy.sparse import coo_matrix
from torch import Tensor

from matspray.data.camera import Camera
from matspray.export.bake import sample_bilinear
from matspray.export.normals import smoothed_vertex_normals, unit_normals
from matspray.export.silhouette import mesh_alpha, spread

REACH = 2.0  # pixels searched either side of a rim vertex for the two silhouettes' edges
STEP = 0.125  # pixels between the samples of that search
OWN_SAMPLES = 4  # samples per pixel side of the mesh's own coverage: its edge to a quarter pixel
ON_RIM = 0.75  # pixels: a rim vertex further than this from the mesh's own edge is inside the outline, no vote
NORMAL_STEP = 1e-3  # world units: the finite step that projects a normal into the image
# views a round looks at, spread over the training views: the step's time grows with them, and on a capture of
# about a hundred views half of them fit the rim as well (docs/dev/export.md)
FIT_VIEWS = 48
# A normal within 30 degrees of the ray moves the vertex's projection by less than half its move: the pixels it
# must travel would ask a long move in depth, which that view does not see
MIN_SIDEWAYS = 0.5


def edge_position(values: Tensor, steps: Tensor, level: float) -> tuple[Tensor, Tensor]:
    # values [R, T] sampled at offsets steps [T] (pixels, increasing outwards) -> offset [R], clean [R] bool
    """Where each line of samples leaves the silhouette: the offset at which `values` fall below `level`, at the
    crossing nearest the line's middle (linear between samples), and whether the line runs cleanly from inside
    (its first sample) to outside (its last); the offset of a line that does not is meaningless."""
    inside = values >= level
    leaves = inside[:, :-1] & ~inside[:, 1:]  # [R, T - 1]
    distance = torch.where(leaves, steps[:-1].abs().expand_as(leaves), torch.inf)
    k = distance.argmin(1)
    rows = torch.arange(len(values))
    before, after = values[rows, k], values[rows, k + 1]
    offset = steps[k] + (steps[1] - steps[0]) * (before - level) / (before - after).clamp_min(1e-6)
    return offset, inside[:, 0] & ~inside[:, -1] & leaves.any(1)


def facing(mesh: trimesh.Trimesh, eye: np.ndarray) -> np.ndarray:  # eye [3] -> [F] bool
    """The faces turned to a camera at `eye`."""
    return ((mesh.triangles_center - eye) * mesh.face_normals).sum(1) < 0


def rim_vertices(mesh: trimesh.Trimesh, facing: np.ndarray) -> np.ndarray:  # facing [F] bool -> [V] bool
    """Vertices on an edge between a face turned to the camera and one turned away: the mesh's contour as the
    camera sees it, hidden stretches included."""
    pairs = mesh.face_adjacency  # [E, 2] faces sharing an edge
    edges = mesh.face_adjacency_edges[facing[pairs[:, 0]] != facing[pairs[:, 1]]]
    rim = np.zeros(len(mesh.vertices), dtype=bool)
    rim[edges.reshape(-1)] = True
    return rim


def faces_near(
    pixels: np.ndarray, faces: np.ndarray, points: np.ndarray, width: int, height: int
) -> np.ndarray:  # pixels [V, 2] projected vertices, faces [F, 3], points [P, 2] -> [F] bool
    """The faces whose projected bounding box touches a pixel within two pixels of one of `points`: all the faces
    that can cover a bilinear tap of those points (the rest of a large image's faces need not be rasterized)."""
    band = np.zeros((height + 2, width + 2), dtype=bool)  # one pixel of margin on each side
    cells = np.clip(np.floor(points).astype(np.int64) + 1, 0, [width + 1, height + 1])
    band[cells[:, 1], cells[:, 0]] = True
    band = binary_dilation(band, iterations=2)
    table = np.pad(band.cumsum(0).cumsum(1), ((1, 0), (1, 0)))  # summed-area table: [i, j] sums band[:i, :j]
    corners = pixels[faces]  # [F, 3, 2]
    lo = np.clip(np.floor(corners.min(1)).astype(np.int64) + 1, 0, [width + 1, height + 1])  # [F, 2] (x, y)
    hi = np.clip(np.floor(corners.max(1)).astype(np.int64) + 2, 0, [width + 2, height + 2])  # one past the end
    inside = (
        table[hi[:, 1], hi[:, 0]] - table[lo[:, 1], hi[:, 0]] - table[hi[:, 1], lo[:, 0]] + table[lo[:, 1], lo[:, 0]]
    )
    return inside > 0


def contour_offsets(
    mesh: trimesh.Trimesh, normals: np.ndarray, camera: Camera, alpha: Tensor, min_alpha: float
) -> tuple[np.ndarray, np.ndarray]:  # normals [V, 3] unit, alpha [H, W] -> offsets [V], voted [V] bool
    """How far (world units, > 0 outwards) each rim vertex must move along its normal for the mesh's silhouette
    edge to sit on the asset's in this view, and which vertices vote (see the module's text)."""
    vertices = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32)
    pixels, z = camera.project(vertices)
    moved, _ = camera.project(vertices + NORMAL_STEP * torch.tensor(np.asarray(normals), dtype=torch.float32))
    direction = (moved - pixels) / NORMAL_STEP  # [V, 2] pixels per world unit along the normal
    speed = direction.norm(dim=1)
    front = facing(mesh, camera.camtoworld[:3, 3].double().numpy())
    focal = 0.5 * float(camera.K[0, 0] + camera.K[1, 1])
    sideways = speed * z / focal  # [V] sine of the angle between the normal and the ray, near the image's centre
    rim = torch.from_numpy(rim_vertices(mesh, front)) & (z > 1e-6) & (sideways >= MIN_SIDEWAYS)
    index = rim.nonzero().squeeze(1)
    steps = torch.arange(-REACH, REACH + 1e-6, STEP)  # [T]
    outwards = direction[index] / speed[index, None]  # [R, 2]
    line = (pixels[index, None] + steps[None, :, None] * outwards[:, None]).reshape(-1, 2)  # [R * T, 2]
    # a closed surface covers with its faces turned to the camera alone what it covers with all, and only the faces
    # near the lines can cover what the lines sample: a few percent of a large image's work
    faces = np.asarray(mesh.faces, dtype=np.int64)
    faces = faces[front & faces_near(pixels.numpy(), faces, line.numpy(), camera.width, camera.height)]
    own = mesh_alpha(np.asarray(mesh.vertices), faces, camera, OWN_SAMPLES)
    found = [
        edge_position(sample_bilinear(image[..., None].float(), line).reshape(len(index), len(steps)), steps, level)
        for image, level in ((alpha, min_alpha), (torch.from_numpy(own), 0.5))
    ]
    (target, target_clean), (edge, edge_clean) = found
    votes = target_clean & edge_clean & (edge.abs() < ON_RIM)
    offsets, voted = np.zeros(len(vertices)), np.zeros(len(vertices), dtype=bool)
    offsets[index[votes].numpy()] = ((target - edge)[votes] / speed[index[votes]]).double().numpy()
    voted[index[votes].numpy()] = True
    return offsets, voted


def neighbour_mean(mesh: trimesh.Trimesh):  # -> sparse [V, V]: row i averages vertex i's neighbours
    # not trimesh.smoothing.laplacian_calculation: it divides by zero on a vertex no face uses and leaves out such
    # vertices at the end of the list, which a decimated mesh may hold; here their row is zero
    edges = np.asarray(mesh.edges_unique)
    n = len(mesh.vertices)
    rows, cols = np.concatenate([edges[:, 0], edges[:, 1]]), np.concatenate([edges[:, 1], edges[:, 0]])
    adjacency = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)).tocsr()
    degree = np.maximum(np.asarray(adjacency.sum(1)).ravel(), 1.0)
    return coo_matrix(adjacency.multiply(1.0 / degree[:, None])).tocsr()


def fit_silhouettes(
    mesh: trimesh.Trimesh,
    cameras: list[Camera],
    alphas: list[Tensor],  # [H, W] per camera: the asset's coverage
    min_alpha: float,
    rounds: int,
    normal_smoothing: int = 10,
    spreading: int = 3,
    views: int = FIT_VIEWS,
) -> trimesh.Trimesh:
    """`mesh` with its vertices moved along their (Taubin-smoothed) normals so that its silhouettes follow the
    asset's: per round, each vertex's `contour_offsets` averaged over the views where it votes, then `spreading`
    passes that blend each move with its neighbours' mean (a vertex that never votes takes the mean). Up to `views` of
    the cameras, spread over them, take part."""
    if rounds <= 0:
        return mesh
    neighbours = neighbour_mean(mesh)
    faces = np.asarray(mesh.faces)
    for _ in range(rounds):
        normals = unit_normals(smoothed_vertex_normals(mesh, normal_smoothing), np.asarray(mesh.vertices))
        total, votes = np.zeros(len(mesh.vertices)), np.zeros(len(mesh.vertices))
        for i in spread(len(cameras), views):
            offsets, voted = contour_offsets(mesh, normals, cameras[i].to("cpu"), alphas[i].cpu(), min_alpha)
            total += offsets
            votes += voted
        move = np.where(votes > 0, total / np.maximum(votes, 1.0), 0.0)
        for _ in range(spreading):
            mean = neighbours @ move
            move = np.where(votes > 0, 0.5 * (move + mean), mean)
        mesh = trimesh.Trimesh(np.asarray(mesh.vertices) + move[:, None] * normals, faces, process=False)
    return mesh
