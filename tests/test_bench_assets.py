"""`matspray bench`: the object list from files and folders (`--assets`), the per-object table, and its seconds."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("pygltflib")

from matspray.batch.demo import BenchObject, asset_objects, procedural_objects, run_bench  # noqa: E402
from matspray.cli import main  # noqa: E402
from matspray.errors import ConfigError  # noqa: E402
from matspray.eval.tables import objects_table, tables_markdown  # noqa: E402
from matspray.method.config import build_config  # noqa: E402


def test_asset_objects_from_files_and_folders(tmp_path):
    (tmp_path / "set" / "deep").mkdir(parents=True)
    for name in ("b.glb", "a.gltf", "deep/c.GLB", "notes.txt"):
        (tmp_path / "set" / name).write_bytes(b"x")
    single = tmp_path / "single.glb"
    single.write_bytes(b"x")
    objects = asset_objects([tmp_path / "set", single])
    assert [o.name for o in objects] == ["00-a", "01-b", "02-c", "03-single"]
    assert [o.seed for o in objects] == [0, 1, 2, 3] and objects[3].asset == str(single)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ConfigError, match="holds no .glb or .gltf"):
        asset_objects([empty])
    with pytest.raises(ConfigError, match="not a .glb/.gltf file"):
        asset_objects([tmp_path / "set" / "notes.txt"])
    assert procedural_objects(2) == [BenchObject("00-composite", "composite", 0), BenchObject("01-blob", "blob", 1)]


def test_objects_table_orders_variants_and_counts_wins():
    rows = {
        "00-a": {
            "source": "a.glb",
            "psnr": {
                "relighting": {"Full": 30.0, "Supervised": 28.0, "Proj. Average": 29.0, "Without Softmax": 31.0},
                "basecolor": {"Full": 25.0},
            },
            "seconds": {"synth": 12.0, "method": 100.0},
        },
        "01-b": {
            "source": "b.glb",
            "psnr": {"relighting": {"Full": 27.0, "Supervised": 28.5, "Proj. Average": 26.0}},
            "seconds": {"synth": 10.0, "method": 90.0},
        },
    }
    table = objects_table(rows)
    assert (
        "| 00-a (a.glb) | 30.00 | 28.00 | 29.00 | **31.00** | Without Softmax > Full > Proj. Average > Supervised | "
        "25.00 | 12.0 | 100.0 |" in table
    )
    assert (
        "| 01-b (b.glb) | 27.00 | **28.50** | 26.00 | — | Supervised > Full > Proj. Average | — | 10.0 | 90.0 |"
        in table
    )
    assert "Full > Supervised (relighting PSNR) on 1 of 2 objects" in table
    assert "Full > Proj. Average (relighting PSNR) on 2 of 2 objects" in table
    assert "Full > Without Softmax (relighting PSNR) on 0 of 1 objects" in table
    assert "## Per object" in tables_markdown({"objects": rows}) and "## Per object" not in tables_markdown({})


def test_bench_refuses_a_bad_asset_before_any_object_is_made(tmp_path, capsys):
    (tmp_path / "set").mkdir()
    (tmp_path / "set" / "broken.glb").write_bytes(b"glTF\x02\x00\x00\x00\xff\x00\x00\x00")
    code = main(["bench", "--assets", str(tmp_path / "set"), "--preset", "test", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and "broken.glb" in err and "truncated" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_bench_reports_each_objects_stage_seconds_also_when_a_rerun_skips_it(tmp_path):
    """Two tiny procedural objects through `run_bench` (in-process batch): the per-object table's
    method seconds are the run's stage seconds, and stay so when a second call skips the finished objects."""
    pytest.importorskip("mitsuba")
    config = build_config("test", predictor="simulated", **{"geometry.iterations": 150, "refine.iterations": 8})
    objects = [BenchObject("00-sphere", "sphere", 0), BenchObject("01-torus", "torus", 1)]
    quiet = dict(preset="test", progress=False, log=lambda *_: None, config=config, use_ray=False)
    for call in range(2):
        summary = run_bench(tmp_path, objects, **quiet)
        assert [o["status"] for o in summary["objects"]] == (["finished"] * 2 if call == 0 else ["skipped"] * 2)
        rows = json.loads((tmp_path / "bench.json").read_text())["tables"]["objects"]
        for obj in objects:
            timings = json.loads((tmp_path / obj.name / "timings.json").read_text())
            assert rows[obj.name]["seconds"]["method"] == pytest.approx(sum(timings.values()))
            assert {"geometry", "lift", "asset"} <= set(timings)
    assert "| 00-sphere (sphere (seed 0)) |" in (tmp_path / "tables.md").read_text()
