import json

import pytest

from benchmarks.tables_shadows import table_no_softmax_forms, table_shadows, table_shadows_mean

OFF = {  # relighting PSNR per object and variant of a pass without the shadows
    "a": {"full": 25.0, "proj-average": 24.0, "no-softmax": 25.5},
    "b": {"full": 27.0, "proj-average": 26.0, "no-softmax": 26.5},
}


def passes(tmp_path, first: dict, second: dict) -> tuple[str, str]:
    """Two generalise results files holding `first` and `second` ({object: {variant: PSNR}}) under `paper`."""
    for name, figures in (("first.json", first), ("second.json", second)):
        objects = [{"object": {"name": n}, "figures": {"relight": relight}} for n, relight in figures.items()]
        (tmp_path / name).write_text(json.dumps({"models": {"paper": {"objects": objects}}}))
    return "first.json", "second.json"


def test_shadow_table_pairs_each_object_and_variant_and_averages_them(tmp_path):
    on = {
        "b": {"full": 28.0, "proj-average": 26.5, "no-softmax": 27.0},
        "a": {"full": 26.0, "proj-average": 24.5, "no-softmax": 26.5},
    }
    lines = table_shadows(tmp_path, passes(tmp_path, OFF, on)).splitlines()
    assert lines[0].startswith("Error model `paper`")
    assert lines[2] == (
        "| object | full off / on | proj-average off / on | no-softmax off / on | full - no-softmax off / on |"
    )
    assert lines[4] == "| a | 25.00 / 26.00 | 24.00 / 24.50 | 25.50 / 26.50 | -0.50 / -0.50 |"
    assert lines[5] == "| b | 27.00 / 28.00 | 26.00 / 26.50 | 26.50 / 27.00 | 0.50 / 1.00 |"
    assert lines[6] == "| **mean of 2** | 26.00 / 27.00 | 25.00 / 25.50 | 26.00 / 26.75 | 0.00 / 0.25 |"


def test_shadow_table_refuses_passes_without_a_common_object(tmp_path):
    other = {"c": {"full": 1.0, "proj-average": 1.0, "no-softmax": 1.0}}
    with pytest.raises(SystemExit, match="share no object"):
        table_shadows(tmp_path, passes(tmp_path, OFF, other))


def test_shadow_mean_table_has_one_row_per_shading_over_the_common_objects(tmp_path):
    on = {"a": {"full": 26.0, "proj-average": 24.5, "no-softmax": 26.5}, "c": {"full": 1.0}}
    assert table_shadows_mean(tmp_path, passes(tmp_path, OFF, on)).splitlines() == [
        "| shading (1 object, `paper`) | full | proj-average | no-softmax |",
        "| --- | ---: | ---: | ---: |",
        "| unshadowed (the default) | 25.00 | 24.00 | 25.50 |",
        "| baked shadows (`--set shadows=on`) | 26.00 | 24.50 | 26.50 |",
    ]


def test_no_softmax_forms_table_puts_the_raw_pass_beside_the_default(tmp_path):
    raw = {"b": {"no-softmax": 26.0}, "a": {"no-softmax": 24.0}}
    assert table_no_softmax_forms(tmp_path, passes(tmp_path, OFF, raw)).splitlines()[2:] == [
        "| a | 25.00 | 25.50 | 24.00 |",
        "| b | 27.00 | 26.50 | 26.00 |",
        "| **mean of 2** | 26.00 | 26.00 | 25.00 |",
    ]
