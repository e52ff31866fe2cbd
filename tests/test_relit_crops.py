"""Relit crops, run beside run: the square around the object, the columns."""

import torch

from matspray.eval.relit_crops import GREY, MARGIN, relit_crops, square_box
from matspray.method.asset import Asset
from matspray.render.shade.envmap import EnvironmentMap
from tests.scenes import ring_cameras, sky_map, sphere_of_disks


def brute_force_box(alphas, margin):
    """The smallest square (with the margin) whose centre is the object's box centre, by checking each side."""
    covered = torch.stack([a >= 0.5 for a in alphas]).any(0)
    rows, cols = torch.nonzero(covered, as_tuple=True)
    extent = max(int(rows.max() - rows.min()), int(cols.max() - cols.min()))
    height, width = covered.shape
    side = next(s for s in range(1, 10_000) if s > extent * (1 + 2 * margin))
    side = min(side, height, width)
    top = sorted((0, (int(rows.min()) + int(rows.max()) - side) // 2, height - side))[1]
    left = sorted((0, (int(cols.min()) + int(cols.max()) - side) // 2, width - side))[1]
    return top, left, side


def test_square_box_holds_every_object_pixel_with_its_margin():
    generator = torch.Generator().manual_seed(0)
    for _ in range(20):
        alphas = []
        for _ in range(2):
            alpha = torch.zeros(40, 60)
            r, c = torch.randint(0, 30, (2,), generator=generator).tolist()
            alpha[r : r + 1 + int(torch.randint(0, 10, (1,), generator=generator)), c : c + 12] = 1.0
            alphas.append(alpha)
        top, left, side = square_box(alphas)
        assert (top, left, side) == brute_force_box(alphas, MARGIN)
        covered = torch.stack(alphas).amax(0) >= 0.5
        assert int(covered[top : top + side, left : left + side].sum()) == int(covered.sum())
    assert square_box([torch.zeros(8, 8)]) is None


def test_relit_crops_put_each_asset_at_the_same_size_over_grey():
    gaussians, normals, materials = sphere_of_disks(300)
    camera = ring_cameras(1, size=48)[0]
    light = EnvironmentMap.from_tensor(sky_map(), learnable=False).prefilter()
    whole = Asset(gaussians, materials, normals)
    keep = gaussians.means[:, 2] > 0  # the upper half alone: a smaller object
    half = Asset(gaussians.subset(keep), materials[keep], normals[keep])
    photo = torch.rand(48, 48, 3, generator=torch.Generator().manual_seed(1))
    row = relit_crops([whole, half], camera, light, photo, size=32)
    assert row.shape == (32, 3 * 32, 3)
    # the crop is the whole sphere's square: the half sphere leaves grey where the whole one has its lower half
    whole_bottom = row[28:, 32 + 12 : 32 + 20]  # bottom middle of the whole sphere's column
    assert float((row[28:, 64 + 12 : 64 + 20] - GREY).abs().max()) < 1e-3
    assert float((whole_bottom - GREY).abs().max()) > 0.05
    assert relit_crops([Asset(gaussians.subset(keep & False), materials[:0], normals[:0])], camera, light) is None


def test_a_synthetic_objects_reference_is_its_relit_truth_and_light(tiny_object):
    from matspray.data import load_scene
    from matspray.data.images import read_image
    from matspray.eval.relit_crops import relit_truth

    view = load_scene(tiny_object).test[0]
    env = sorted(p.stem.removeprefix(f"{view.name}_relight_") for p in view.path.parent.glob(f"{view.name}_relight_*"))[
        0
    ]
    image, light = relit_truth(view, env, tiny_object)
    rgb, alpha = read_image(view.path.with_name(f"{view.name}_relight_{env}.png"))
    assert alpha is not None and bool((alpha < 0.5).any())
    torch.testing.assert_close(image, rgb * alpha[..., None] + GREY * (1 - alpha[..., None]))  # over grey
    expected = EnvironmentMap.from_file(tiny_object / "envmaps" / f"{env}.exr", height=64)  # as `matspray eval` lights
    torch.testing.assert_close(light.log_map, expected.log_map)
    assert (
        relit_truth(view, "no-such-light", tiny_object) is None
    )  # a capture's view, or a light it was not relit under
