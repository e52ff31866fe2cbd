"""`--method paper` is the paper: every setting where the two methods resolve differently is a row of
`presets.ADDITIONS`, holding the paper's value and its source, and the settings the text leaves to the released code
are the same in both methods."""

from __future__ import annotations

import re
from dataclasses import fields, is_dataclass
from pathlib import Path

import pytest

from matspray.method.config import build_config, variant_refine_config
from matspray.presets import ADDITIONS, PRESETS, RELEASED, RELEASED_VALUES, VARIANT_NAMES

PAPER = "../shared/paper/matspray.tex"  # the paper's text, whose lines the sources name (a developer's tree only)
PAPER_TEXT = Path(__file__).resolve().parents[1] / PAPER


def flattened(config, prefix: str = "") -> dict:
    """Every setting of a (nested) frozen config by dotted name -> value."""
    out = {}
    for f in fields(config):
        value = getattr(config, f.name)
        if is_dataclass(value):
            out |= flattened(value, f"{prefix}{f.name}.")
        else:
            out[f"{prefix}{f.name}"] = value
    return out


def differences(a, b, prefix: str = "") -> dict:
    """Dotted name -> (a's value, b's value) wherever they differ (settings present in one only included)."""
    fa, fb = flattened(a, prefix), flattened(b, prefix)
    return {k: (fa.get(k), fb.get(k)) for k in fa.keys() | fb.keys() if fa.get(k) != fb.get(k)}


def unlisted(ours, paper, prefix: str = "") -> dict:
    """The differences between the methods' configs that no row of ADDITIONS names (`prefix`: the configs' place)."""
    rows = {a.setting for a in ADDITIONS}
    return {k: v for k, v in differences(ours, paper, prefix).items() if k != "method" and k not in rows}


@pytest.mark.parametrize("preset", PRESETS)
def test_every_difference_between_the_methods_has_a_row_with_the_papers_value(preset):
    ours, paper = build_config(preset), build_config(preset, "paper")
    assert unlisted(ours, paper) == {}
    for variant in VARIANT_NAMES:  # the refinement as each variant runs it
        refined = variant_refine_config(ours, variant), variant_refine_config(paper, variant)
        assert unlisted(*refined, prefix="refine.") == {}
    resolved = flattened(paper)
    for addition in ADDITIONS:
        assert resolved[addition.setting] == addition.paper, addition.name


def test_the_table_check_finds_a_difference_without_a_row():
    """The check itself fails where the methods differ in a setting no row names (here the merger's width)."""
    ours, paper = build_config("demo"), build_config("demo", "paper", **{"refine.merger.hidden": 64})
    assert set(unlisted(ours, paper)) == {"refine.merger.hidden"}


def test_each_row_changes_its_setting_and_names_its_source():
    ours = flattened(build_config("demo"))
    for addition in ADDITIONS:
        assert ours[addition.setting] != addition.paper, f"{addition.name} is not a difference"
        assert addition.source.startswith(("l.", "eq.", RELEASED)), addition.name
    assert len({a.setting for a in ADDITIONS}) == len(ADDITIONS) == len({a.name for a in ADDITIONS})


@pytest.mark.skipif(not PAPER_TEXT.exists(), reason=f"the paper's text is not at {PAPER} (outside a developer's tree)")
def test_the_sources_name_lines_of_the_papers_text():
    lines = PAPER_TEXT.read_text().splitlines()
    for addition in ADDITIONS:
        for line in re.findall(r"l\.(\d+)", addition.source):
            assert 1 <= int(line) <= len(lines) and lines[int(line) - 1].strip(), (addition.name, line)
    text = "\n".join(lines)
    assert "100{,}000$ points sampled uniformly at random" in text  # hull-init's source, l.209
    assert "train Gaussian Splatting on DiffusionRenderer normals" in text  # geometry-normals' source, l.213


def test_where_the_text_is_silent_both_methods_take_the_released_codes_value():
    for preset in PRESETS:
        ours, paper = flattened(build_config(preset)), flattened(build_config(preset, "paper"))
        for path, value, source in RELEASED_VALUES:
            assert ours[path] == paper[path] == value, (preset, path)
            assert source.startswith(RELEASED)


def test_the_paper_starts_a_masked_object_from_random_points_and_trains_no_predicted_normals():
    paper = build_config("paper", "paper")
    assert paper.geometry.init == "random" and paper.geometry.init_points == 100_000  # l.209
    assert paper.geometry.predicted_normal_weight == 0 and paper.refine.predicted_normal_weight == 0
    assert paper.refine.merger.frequencies == 4 and paper.refine.merger.precision == "float32"
    assert paper.lift.footprint_sigmas == 1.0 and paper.refine.photo_weight == 2.0  # the released code's
    # a user's setting wins over the paper's value, in geometry too (it was overwritten by the method before)
    specular = build_config("demo", "paper", **{"geometry.predicted_normal_weight": 1.0})
    assert specular.geometry.predicted_normal_weight == 1.0


def test_the_defaults_fingerprint_follows_every_default_and_nothing_of_one_run(monkeypatch):
    from matspray import presets
    from matspray.method.config import defaults_fingerprint

    demo, paper = defaults_fingerprint("demo"), defaults_fingerprint("demo", "paper")
    assert demo != paper and demo == defaults_fingerprint("demo")
    monkeypatch.setitem(presets.PRESET_SETTINGS, "demo", {"refine": {"iterations": 601}})
    assert defaults_fingerprint("demo") != demo  # a changed default is another set of defaults


def test_the_papers_softmax_ablation_is_its_merger_with_the_softmax_taken_out():
    import torch

    from matspray.method.merger import projection_average
    from matspray.method.refine.sources import MergerSource
    from matspray.presets import get_variant

    paper, ours = build_config("demo", "paper"), build_config("demo")
    assert variant_refine_config(paper, "no-softmax").merger.unconstrained == "raw"
    assert variant_refine_config(ours, "no-softmax").merger.unconstrained == "offset"
    # the variants that do not read the rule record it at its default: their stages keep their fingerprints
    for name in set(VARIANT_NAMES) - {"no-softmax"}:
        assert variant_refine_config(paper, name).merger.unconstrained == "offset", name
    g = torch.Generator().manual_seed(0)
    positions, values, seen = torch.rand(40, 3, generator=g), torch.rand(40, 5, 5, generator=g), torch.ones(40, 5) > 0
    bounds = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    average = projection_average(values, seen)
    for config, starts_at_average in ((paper, False), (ours, True)):
        torch.manual_seed(0)
        merger = variant_refine_config(config, "no-softmax").merger
        source = MergerSource(get_variant("no-softmax"), positions, values, seen, bounds, merger)
        with torch.no_grad():
            merged = source.merger(positions, values, seen)
        assert torch.allclose(merged, average, atol=1e-6) == starts_at_average


def test_a_variant_records_the_settings_only_other_variants_read_as_the_table_says():
    from matspray.method.config import setting_default

    config = build_config("demo", "paper", **{"refine.metallic_prior_weight": 0.2})  # paper: unconstrained "raw"
    assert setting_default(config.refine, "merger.unconstrained") == "offset"  # the field's own, not the paper's
    assert setting_default(config.refine, "metallic_prior_weight") == 0.01
    recorded = {
        name: (refine.metallic_prior_weight, refine.metallic_prior_start, refine.merger.unconstrained)
        for name in VARIANT_NAMES
        for refine in [variant_refine_config(config, name)]
    }
    assert recorded.pop("photos-only") == (0.2, 0.1, "offset")
    assert recorded.pop("no-softmax") == (0.0, 0.5, "raw")
    assert set(recorded.values()) == {(0.0, 0.5, "offset")}
