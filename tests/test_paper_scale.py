"""benchmarks.paper_scale's report lines: what each stage really ran on, and the frozen views at the paper's scale."""

import json

from benchmarks.paper_scale import PAPER_PIXELS, PAPER_VIEWS, frozen_lines, stage_lines
from matspray.render.raster.gbuffer import frozen_views_bytes
from matspray.rundir import RunDir


def test_each_stage_line_says_its_device_backend_and_renderers(tmp_path):
    records = {
        "geometry": {"device": "cuda:0", "backend": "gsplat", "renders": {"gsplat": 30005}},
        "lift": {"device": "cuda:0", "backend": "gsplat", "renders": {"rays": 100}},
        "materials2d": {"fingerprint": "x"},
    }  # a stage that renders nothing has no device record: left out
    for stage, record in records.items():
        (tmp_path / stage).mkdir()
        (tmp_path / stage / "stage.json").write_text(json.dumps(record))
    assert stage_lines(RunDir(tmp_path)) == [
        "  geometry   device cuda:0, backend gsplat: gsplat x30005",
        "  lift       device cuda:0, backend gsplat: rays x100",
    ]


def test_frozen_views_scale_to_the_paper_and_say_where_they_are_kept():
    measured = {
        "backend": "torch",
        "bytes": 556407152,
        "hits": 22432898,
        "gaussians": 39919,
        "pixels": 655360,
        "views": 40,
        "views_on_host": 0,
    }
    lines = frozen_lines(measured)
    paper = frozen_views_bytes(round(22432898 / 655360 * PAPER_VIEWS * PAPER_PIXELS), PAPER_PIXELS, 39919, PAPER_VIEWS)
    assert f"{paper / 2**30:.2f} GiB (estimate) -> kept on the GPU" in lines[1]  # 16 bytes a hit: fits 24 GB
    assert "530.6 MiB for 40 views (34.2 weights per pixel" in lines[0]
    dense = dict(measured, hits=measured["hits"] * 3 // 2)  # half as dense again does not
    assert frozen_lines(dense)[1].endswith("-> kept on the host, copied to the GPU view by view")
    assert frozen_lines(dict(measured, backend="gsplat")) == [
        "  refinement keeps no blend matrices (gsplat renders each step again)"
    ]
    assert frozen_lines(None) == ["  refinement kept no frozen views"]
