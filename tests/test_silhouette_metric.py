"""The silhouette-counting (union) figure next to the object-mask (GT) one, against hand-computed values."""

import math
from dataclasses import replace
from types import SimpleNamespace

import pytest
import torch

from matspray.data.images import linear_to_srgb
from matspray.errors import DataError
from matspray.eval.evaluate import evaluate_images, pooled_union_psnr
from matspray.eval.glb import relighting_gap_line
from matspray.eval.masked import covered_box, union_weights
from matspray.eval.run_eval import GroundTruth, ViewRenders, evaluate_predictions, paper_tables, score_renders
from matspray.eval.tables import UNION_LABEL, average_tables, material_table, tables_markdown
from matspray.metrics import ssim
from matspray.predictors.maps import MaterialMaps

SIZE = 16


def square(first: int = 4, last: int = 12, size: int = SIZE) -> torch.Tensor:  # [H, W] with a filled square
    mask = torch.zeros(size, size, dtype=torch.float64)
    mask[first:last, first:last] = 1.0
    return mask


def grey(value: float, size: int = SIZE, channels: int = 3) -> torch.Tensor:  # [H, W, C]
    return torch.full((size, size, channels), value, dtype=torch.float64)


# ------------------------------------------------------------------------------------------ PSNR by hand
def test_extra_pixels_outside_the_true_mask_cost_only_under_the_union():
    truth, mask = grey(0.5), square()  # object: 8 x 8 = 64 pixels
    alpha = mask.clone()
    alpha[4:12, 12:14] = 1.0  # the prediction paints 16 pixels more, right of the object
    gt = evaluate_images(truth, truth, mask)  # prediction == truth inside the true mask
    union = evaluate_images(truth, truth, mask, pred_alpha=alpha)
    assert gt == {"psnr": math.inf, "ssim": pytest.approx(1.0), "lpips": None}
    # the 16 extra pixels show the object's colour (sRGB of 0.5) where the truth shows the white background
    difference = 1.0 - float(linear_to_srgb(torch.tensor(0.5, dtype=torch.float64)))
    expected_mse = 16 * difference**2 / 80  # over the union: 64 + 16 pixels
    assert union["psnr"] == pytest.approx(-10 * math.log10(expected_mse), rel=1e-9)
    assert union["ssim"] < 1.0


def test_a_missing_part_of_the_silhouette_costs_only_under_the_union():
    truth, mask = grey(0.2, channels=1), square()
    alpha = mask.clone()
    alpha[4:8, 4:8] = 0.0  # 16 of the 64 object pixels not covered; the straight colour is right there
    gt = evaluate_images(truth, truth, mask, encoding="raw")
    union = evaluate_images(truth, truth, mask, encoding="raw", pred_alpha=alpha)
    assert gt["psnr"] == math.inf
    expected_mse = 16 * (1.0 - 0.2) ** 2 / 64  # background 1 where the truth has 0.2; union = the true mask
    assert union["psnr"] == pytest.approx(-10 * math.log10(expected_mse), rel=1e-9)


def test_a_soft_halo_counts_with_its_alpha_in_the_composite_and_in_the_weights():
    truth, mask = grey(0.2, channels=1), square()
    alpha = mask.clone()
    alpha[4:12, 12:14] = 0.5  # a half-transparent fringe of 16 pixels
    union = evaluate_images(truth, truth, mask, encoding="raw", pred_alpha=alpha)
    # fringe: 0.5 * 0.2 + 0.5 * 1 = 0.6 against the background 1; weight max(0.5, 0) = 0.5 each
    expected_mse = 16 * 0.5 * 0.4**2 / (64 + 16 * 0.5)
    assert union["psnr"] == pytest.approx(-10 * math.log10(expected_mse), rel=1e-9)
    assert torch.equal(union_weights(alpha, mask), torch.maximum(alpha, mask))


def test_with_the_true_silhouette_both_figures_agree_up_to_the_region():
    truth, mask = grey(0.2, channels=1), square()
    pred = truth + 0.1  # wrong everywhere by 0.1
    gt = evaluate_images(pred, truth, mask, encoding="raw")
    union = evaluate_images(pred, truth, mask, encoding="raw", pred_alpha=mask)
    assert union["psnr"] == pytest.approx(20.0)  # mse 0.01 over the object
    # the GT figure averages the same error over the full image: 64 of 256 pixels
    assert gt["psnr"] == pytest.approx(20.0 + 10 * math.log10(SIZE * SIZE / 64))
    assert evaluate_images(truth, truth, mask, pred_alpha=mask) == evaluate_images(truth, truth, mask)


# ------------------------------------------------------------------------------------------ SSIM, LPIPS region
def test_weighted_ssim_is_the_plain_mean_for_a_full_mask_and_ignores_windows_off_the_region():
    generator = torch.Generator().manual_seed(3)
    x = torch.rand(32, 32, 3, generator=generator, dtype=torch.float64)
    y = torch.rand(32, 32, 3, generator=generator, dtype=torch.float64)
    assert ssim(x, y, torch.ones(32, 32)) == pytest.approx(ssim(x, y), rel=1e-12)
    far = y.clone()
    far[:, :16] = x[:, :16]  # identical on the left half, different on the right
    region = torch.zeros(32, 32)
    region[:, :5] = 1.0  # every window touching it lies within the identical half (columns < 16)
    assert ssim(x, far, region) == pytest.approx(1.0, abs=1e-12)
    assert ssim(x, far) < 0.9
    with pytest.raises(DataError, match="empty region"):
        ssim(x, y, torch.zeros(32, 32))


def test_covered_box_grows_to_the_minimum_size_inside_the_image():
    weights = torch.zeros(40, 50)
    weights[2:4, 45:48] = 0.3
    assert covered_box(weights, 31) == (slice(0, 31), slice(19, 50))
    weights[1:39, 1:49] = 1.0
    assert covered_box(weights, 31) == (slice(1, 39), slice(1, 49))  # already larger: the tight box
    assert covered_box(torch.ones(20, 20), 31) == (slice(0, 20), slice(0, 20))  # smaller image: all of it
    with pytest.raises(DataError, match="empty"):
        covered_box(torch.zeros(5, 5))


class RecordingMetric:
    source = "test double"

    def __init__(self):
        self.shapes = []

    def distance(self, pred, target):
        self.shapes.append(tuple(pred.shape))
        return float((pred - target).abs().mean())


def test_lpips_of_the_union_figure_sees_the_union_box():
    metric = RecordingMetric()
    truth, mask = grey(0.5, size=64), square(20, 30, size=64)
    alpha = mask.clone()
    alpha[20:30, 30:40] = 1.0
    evaluate_images(truth, truth, mask, lpips=metric)
    evaluate_images(truth, truth, mask, lpips=metric, pred_alpha=alpha)
    assert metric.shapes == [(64, 64, 3), (31, 31, 3)]  # full image; union 10 x 20 grown to 31 x 31


# ------------------------------------------------------------------------------------------ metallic, pooled
def test_pooled_union_psnr_by_hand():
    mask = square()
    truth = mask * 0.5  # metallic 0.5 on the object
    alpha = mask.clone()
    alpha[4:12, 12:14] = 1.0  # view 0 paints 16 extra pixels with metallic 0.5 (black background: truth 0)
    assert pooled_union_psnr([truth, truth], [mask, mask], [truth, truth], [mask, mask]) == math.inf
    value = pooled_union_psnr([torch.full((SIZE, SIZE), 0.5)] * 2, [alpha, mask], [truth, truth], [mask, mask])
    assert value == pytest.approx(-10 * math.log10(16 * 0.25 / (80 + 64)), rel=1e-9)


# ------------------------------------------------------------------------------------------ end to end
def fake_object(extra: bool):
    mask = square()
    truth = GroundTruth(
        mask=mask.float(),
        basecolor=grey(0.5).float(),
        roughness=torch.full((SIZE, SIZE), 0.5),
        metallic=(mask * 0.5).float(),
        relit={"sky": grey(0.5).float()},
    )
    alpha = mask.clone()
    if extra:
        alpha[4:12, 12:14] = 1.0
    render = ViewRenders(
        relit={"sky": grey(0.5).float()},
        base_color=grey(0.5).float(),
        roughness=torch.full((SIZE, SIZE), 0.5),
        metallic=torch.full((SIZE, SIZE), 0.5),
        alpha=alpha.float(),
    )
    return SimpleNamespace(name="v0"), truth, render


def test_score_renders_reports_both_figures_under_distinct_keys():
    view, truth, render = fake_object(extra=True)
    summary = score_renders([render], [view], [truth], ["sky"], None, aligned=True)["summary"]
    assert (
        summary["relighting"]["psnr"] == math.inf and summary["basecolor"]["psnr"] == math.inf
    )  # GT mask: blind to it
    difference = 1.0 - float(linear_to_srgb(torch.tensor(0.5, dtype=torch.float64)))
    expected = -10 * math.log10(16 * difference**2 / 80)
    for key in ("relighting_union", "relighting_sky_union", "basecolor_union", "relighting_aligned_union"):
        assert summary[key]["psnr"] == pytest.approx(expected, rel=1e-6), key
    assert summary["roughness_union"]["psnr"] == pytest.approx(-10 * math.log10(16 * 0.25 / 80), rel=1e-6)
    # metallic, pooled on black: 16 extra pixels at 0.5 against 0, over the 80 of the union
    assert summary["metallic_union"]["psnr"] == pytest.approx(-10 * math.log10(16 * 0.25 / 80), rel=1e-6)
    assert summary["metallic_union"]["psnr_infinite"] == 0 and summary["metallic"]["psnr_infinite"] == 1
    view, truth, render = fake_object(extra=False)
    exact = score_renders([render], [view], [truth], ["sky"], None)["summary"]
    for key in ("relighting", "relighting_union"):  # identical images and silhouettes: equal under both
        assert exact[key] == {"psnr": math.inf, "ssim": pytest.approx(1.0), "lpips": None}


def test_tables_and_averages_show_both_figures():
    per_object = []
    for extra in (True, False):
        view, truth, render = fake_object(extra)
        scored = score_renders([render], [view], [truth], ["sky"], None)
        per_object.append({"notes": [], **paper_tables({"full": scored, "proj-average": scored}, None, {})})
    table1 = per_object[0]["table1"]["Ours"]
    assert {"relighting", "relighting_union", "metallic", "metallic_union"} <= set(table1)
    assert per_object[0]["table2_union"]["Full"]["psnr"] == table1["relighting_union"]["psnr"]
    text = material_table(per_object[0]["table1"])
    lines = text.splitlines()
    assert lines[2].startswith("| Relighting | ∞ |")
    assert lines[3].startswith(f"| Relighting, {UNION_LABEL} | 18.5")  # right below its GT-mask row
    assert "Rows without a suffix: object mask (GT)" in text
    averaged = average_tables(per_object)
    finite = per_object[0]["table1"]["Ours"]["metallic_union"]["psnr"]
    assert averaged["table1"]["Ours"]["metallic_union"] == {
        "psnr": pytest.approx(finite),
        "ssim": pytest.approx((table1["metallic_union"]["ssim"] + 1.0) / 2),
        "lpips": None,
        "psnr_infinite": 1,
        "objects": 2,
    }
    assert averaged["table1"]["Ours"]["relighting_union"]["psnr"] == math.inf  # one object exact
    assert averaged["table2_union"]["Full"]["psnr"] == math.inf
    assert "table2_union" not in average_tables([{"table2": {"Full": {"psnr": 20.0}}}])  # older metrics.json: none
    document = tables_markdown(averaged)
    assert f"## Table 2, {UNION_LABEL}" in document and f"Metallic, {UNION_LABEL} | ∞*/" in document
    assert "(union)" not in tables_markdown(
        {"table1": {"Ours": {"relighting": {"psnr": 20.0}}}}
    )  # old files: as before


def test_the_mesh_gap_line_states_both_gaps():
    gaussians = {"relighting": {"psnr": 24.33}, "relighting_union": {"psnr": 16.9}}
    mesh = {"relighting": {"psnr": 25.10}, "relighting_union": {"psnr": 14.5}}
    assert relighting_gap_line(gaussians, mesh) == (
        "Relighting PSNR of the mesh is below the Gaussian asset's by -0.77 dB under "
        f"the object mask (GT) and 2.40 dB under the {UNION_LABEL} (negative: above)."
    )


def test_score_renders_reports_the_normals_angle_on_the_object_unsigned():
    """Rendered normals 30 degrees off on the object (and flipped: a shading normal has no sign), anything off it:
    the mean error is 30 degrees; without true normals there is no figure."""
    view, truth, render = fake_object(extra=False)
    angle = math.radians(30.0)
    true_normal, rendered = torch.tensor([0.0, 0.0, 1.0]), torch.tensor([math.sin(angle), 0.0, -math.cos(angle)])
    normals = torch.where(square()[..., None] > 0, rendered, torch.tensor([1.0, 0.0, 0.0]))
    truth = replace(truth, normals=true_normal.expand(SIZE, SIZE, 3))
    render = replace(render, normals=3.0 * normals)  # blended normals are not unit
    summary = score_renders([render], [view], [truth], ["sky"], None)["summary"]
    assert summary["normals"]["error_deg"] == pytest.approx(30.0, abs=1e-3) and summary["normals"]["views"] == 1
    assert "normals" not in score_renders([replace(render, normals=None)], [view], [truth], ["sky"], None)["summary"]


def test_2d_metallic_is_pooled_over_the_views_as_the_3d_one_is():
    """Spurious metal in one view of four: the mean of the views' PSNRs forgives it (three exact views are
    infinite), the pooled figure does not. The 2D predictions' metallic follows the 3D assets' pooled rule."""
    mask = square()  # 64 object pixels of 256
    truth = GroundTruth(
        mask=mask.float(), basecolor=grey(0.5).float(), roughness=mask * 0.5, metallic=mask * 0.0, relit={}
    )
    exact = MaterialMaps(basecolor=grey(0.5).float(), roughness=mask * 0.5, metallic=mask * 0.0)
    spurious = replace(exact, metallic=mask * 0.3)
    views = [SimpleNamespace(name=f"v{i}") for i in range(4)]
    maps = {"v0": spurious, "v1": exact, "v2": exact, "v3": exact}
    metallic = evaluate_predictions(maps, views, [truth] * 4, None)["metallic"]
    # pooled on black over the four full images: 64 pixels off by 0.3 among 4 x 256
    assert metallic["psnr"] == pytest.approx(-10 * math.log10(64 * 0.09 / (4 * 256)), rel=1e-6)
    assert metallic["psnr_infinite"] == 0 and metallic["psnr_views"] == math.inf
    # the same maps as a 3D asset's renders get the same figure
    renders = [
        ViewRenders(relit={}, base_color=grey(0.5).float(), roughness=mask * 0.5, metallic=m.metallic, alpha=mask)
        for m in maps.values()
    ]
    scored = score_renders(renders, views, [truth] * 4, [], None)["summary"]["metallic"]
    assert scored["psnr"] == pytest.approx(metallic["psnr"], rel=1e-9)
    exact_only = evaluate_predictions({v.name: exact for v in views}, views, [truth] * 4, None)["metallic"]
    assert exact_only["psnr"] == math.inf and exact_only["psnr_infinite"] == 1  # the paper's infinity rule
