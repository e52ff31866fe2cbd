"""The parts of the report page (matspray.eval.page) and the sharpness figure, checked against values worked out by
hand: no run or browser needed (tests/test_report_browser.py opens a real report in chromium)."""

import json
import math
import re

import pytest
import torch

from matspray.errors import DataError
from matspray.eval.page.glossary import glossary_html
from matspray.eval.page.paths import lpips_line, object_name, page_places, without_machine_paths
from matspray.eval.page.plot import linear_ticks, log_ticks, loss_curves_svg
from matspray.eval.page.summary import ablation_verdicts, headline_table, verdicts_html
from matspray.metrics import gradient_energy


def test_gradient_energy_is_the_weighted_sum_of_squared_neighbour_differences():
    image = torch.tensor([[0.0, 0.5, 0.5], [1.0, 0.25, 0.5]])  # [2, 3], one channel
    mask = torch.tensor([[1.0, 1.0, 0.0], [1.0, 0.5, 1.0]])
    # across: (0.5-0)^2 * 1*1 + (0.5-0.5)^2 * 1*0 + (0.25-1)^2 * 1*0.5 + (0.5-0.25)^2 * 0.5*1
    #       = 0.25 + 0 + 0.28125 + 0.03125
    # down:   (1-0)^2 * 1*1 + (0.25-0.5)^2 * 1*0.5 + (0.5-0.5)^2 * 0*1 = 1 + 0.03125 + 0
    assert gradient_energy(image, mask) == pytest.approx(0.25 + 0.28125 + 0.03125 + 1.0 + 0.03125)
    colour = torch.stack([image, 2 * image.clamp(max=0.5)], dim=-1)  # channels add up
    assert gradient_energy(colour, mask) == pytest.approx(
        gradient_energy(image, mask) + gradient_energy(2 * image.clamp(max=0.5), mask)
    )
    assert gradient_energy(torch.full((4, 4, 3), 0.3), torch.ones(4, 4)) == 0.0  # no detail in a flat image


def test_a_blurred_image_holds_less_gradient_energy_than_the_sharp_one():
    generator = torch.Generator().manual_seed(0)
    sharp = torch.rand(32, 32, 3, generator=generator)
    blurred = torch.nn.functional.avg_pool2d(sharp.permute(2, 0, 1)[None], 3, 1, 1, count_include_pad=False)
    mask = torch.zeros(32, 32)
    mask[4:28, 4:28] = 1
    share = gradient_energy(blurred[0].permute(1, 2, 0), mask) / gradient_energy(sharp, mask)
    assert 0.0 < share < 0.3


def test_gradient_energy_refuses_a_mask_of_another_size():
    with pytest.raises(DataError, match="does not match the image's"):
        gradient_energy(torch.zeros(4, 4, 3), torch.ones(4, 5))


def test_the_machines_paths_are_written_as_places_or_their_last_part():
    places = {"/tmp/x/run": ".", "/tmp/x/data": "the dataset (data)", "/root": "~"}
    text = (
        "<p>run /tmp/x/run/eval/metrics.json of /tmp/x/data, LPIPS at /root/.cache/torch/hub/a.pth and "
        '(/work/shared/lpips/w.npz)</p><svg xmlns="http://www.w3.org/2000/svg"><rect/></svg> 1/2 </b>'
    )
    assert without_machine_paths(text, places) == (
        "<p>run ./eval/metrics.json of the dataset (data), LPIPS at ~/.cache/torch/hub/a.pth and "
        '(…/w.npz)</p><svg xmlns="http://www.w3.org/2000/svg"><rect/></svg> 1/2 </b>'
    )
    assert page_places("/tmp/x/run", "/tmp/x/data")["/tmp/x/run"] == "."
    assert without_machine_paths("at /rootfs/a and /root", {"/root": "~"}) == "at …/a and ~"  # whole folders only


def test_the_lpips_line_says_how_to_get_the_weights_without_the_caches_path():
    line = lpips_line("n/a: torchvision's AlexNet weights are not at /root/.cache/torch/hub/checkpoints/alexnet.pth")
    assert "python -m matspray.eval.lpips --download" in line and "/root" not in line and "alexnet.pth" not in line
    assert lpips_line("matspray AlexNet LPIPS v0.1, weights /work/x/lpips.npz") == (
        "matspray AlexNet LPIPS v0.1, weights …/lpips.npz"
    )


def test_the_object_is_named_by_its_scene_record_or_its_folder(tmp_path):
    synth = tmp_path / "demo" / "data"
    synth.mkdir(parents=True)
    (synth / "scene.json").write_text(json.dumps({"shape": "composite", "seed": 3}))
    assert object_name(synth) == "composite (seed 3)"
    (synth / "scene.json").write_text(json.dumps({"shape": "asset", "asset": {"file": "/a/b/DamagedHelmet.glb"}}))
    assert object_name(synth) == "DamagedHelmet"
    capture = tmp_path / "skull" / "data"  # a dataset folder named 'data': its parent names the object
    capture.mkdir(parents=True)
    assert object_name(capture) == "skull"
    assert object_name(tmp_path / "skull") == "skull"


def test_ticks_are_round_values_inside_the_range():
    assert linear_ticks(0, 30) == [0, 5, 10, 15, 20, 25, 30]
    assert linear_ticks(0.101, 0.215) == pytest.approx([0.12, 0.14, 0.16, 0.18, 0.2])  # a narrow range: linear
    assert log_ticks(0.003, 0.6) == pytest.approx([0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5])  # decades: 1, 2, 5


def test_the_loss_plot_has_labelled_axes_and_ticks_at_the_round_values():
    history = [{"step": s, "material": 0.2 / (1 + s / 10), "photo": 0.11 + 0.001 * s} for s in (0, 10, 20, 30)]
    svg = loss_curves_svg({"full": history})
    assert "refinement step" in svg and "loss (log scale)" in svg
    labels = re.findall(r">([^<]*)</text>", svg)
    for tick in ("0", "5", "10", "15", "20", "25", "30", "0.05", "0.1", "0.2"):  # losses from 0.05 to 0.2
        assert tick in labels, (tick, labels)


TABLE1 = {
    "Ours": {
        "relighting": {"psnr": 27.1, "ssim": 0.9, "lpips": 0.08},
        "basecolor": {"psnr": 22.0},
        "roughness": {"psnr": 15.0},
        "metallic": {"psnr": math.inf, "psnr_infinite": 1},  # one object, all zero metallic: '∞*/∞'
    },
    "No prior (R3DGS-like)": {"relighting": {"psnr": 25.0, "ssim": 0.8, "lpips": None}, "basecolor": {"psnr": 18.0}},
    "2D predictions": {"basecolor": {"psnr": 23.0}, "roughness": {"psnr": 14.0}, "metallic": {"psnr": 20.0}},
}


def test_the_headline_table_holds_each_method_in_a_row_the_best_bold():
    lines = headline_table(TABLE1).splitlines()
    assert lines[0].startswith("|  | Relighting PSNR ↑ | SSIM ↑ | LPIPS ↓ | Base colour PSNR ↑")
    assert lines[2] == "| Ours | **27.100** | **0.900** | 0.080 | 22.000 | **15.000** | ∞*/∞ |"
    assert lines[3] == "| No prior (R3DGS-like) | 25.000 | 0.800 | n/a | 18.000 | — | — |"
    assert lines[4] == "| 2D predictions | — | — | — | **23.000** | 14.000 | 20.000 |"


def variants(**psnr):
    return {name.replace("_", "-"): {"summary": {"relighting": {"psnr": v}}} for name, v in psnr.items()}


def test_each_ablation_line_says_whether_it_agrees_with_the_paper_and_says_so_when_not():
    lines = ablation_verdicts(variants(full=19.48, no_softmax=20.68, proj_average=19.40, supervised=18.0))
    text = dict((line.split(":")[0], (line, agrees)) for line, agrees in lines)
    softmax, agrees = text["Full vs Without Softmax"]
    assert agrees is False and "does NOT agree with the paper" in softmax
    assert "Without Softmax beats Full by 1.2 dB here (20.7 vs 19.5)" in softmax and "paper: 27.3 vs 24.6" in softmax
    assert text["Full vs Proj. Average"][1] is True and "Full ahead by 0.1 dB" in text["Full vs Proj. Average"][0]
    assert text["Full vs Supervised"][1] is True
    assert "Full vs No prior (R3DGS-like)" not in text  # not in this run: no line
    tie = ablation_verdicts(variants(full=19.48, no_prior=19.46))
    assert tie[0][1] is None and "a tie here" in tie[0][0]
    assert ablation_verdicts(variants(no_prior=19.0)) == []  # nothing to compare with without Full
    assert "relighting-gap.md" in verdicts_html(variants(full=19.48, no_softmax=20.68))  # a disagreement: where to read
    assert "relighting-gap.md" not in verdicts_html(variants(full=19.48, no_softmax=19.0))


def test_the_glossary_lists_the_terms_the_page_uses_and_only_those():
    page = "<p>No prior (R3DGS-like), split-sum shading, PSNR; Relighting, object + silhouette (union)</p>"
    glossary = glossary_html(page)
    for term in ("R3DGS-like", "split-sum", "PSNR", "object + silhouette (union)"):
        assert f"<dt>{term}</dt>" in glossary
    assert "<dt>SSIM</dt>" not in glossary and "<dt>LPIPS</dt>" not in glossary
    assert glossary_html("<p>nothing</p>") == ""
    assert "<dt>Photos only</dt>" in glossary_html("<td>Photos only</td>")  # the asset a run without maps makes


def test_a_small_estimated_light_is_shown_smooth_at_the_evaluation_size():
    from matspray.eval.report import as_shaded

    constant = torch.full((8, 16, 3), 0.7)
    shown = as_shaded(constant, 64)
    assert shown.shape == (64, 128, 3) and torch.allclose(shown, constant[:1, :1].expand(64, 128, 3))
    ramp = torch.arange(16.0).repeat(8, 1)[..., None].expand(8, 16, 3)  # columns 0..15 (wrapping 15 -> 0)
    shown = as_shaded(ramp, 64)[32, :, 0]
    # bilinear: output column j (centre u = (j + 0.5) / 128) reads the ramp at u * 16 - 0.5 between its centres, so
    # it rises by 1/8 a column, not in 1-unit blocks; at the edges it wraps (blends column 15 with column 0)
    j = torch.arange(4, 124)
    assert torch.allclose(shown[j], (j + 0.5) / 8 - 0.5, atol=1e-4)
    assert 0.0 < float(shown[0]) < 15.0 and 0.0 < float(shown[127]) < 15.0
