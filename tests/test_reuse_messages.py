"""'done before, reusing' is said of what a run did not make: once per stage, and never right after making it."""

from __future__ import annotations

import pytest

from matspray.method.config import build_config
from matspray.method.pipeline import Pipeline


@pytest.mark.slow  # a run of the test preset, twice
def test_done_before_is_said_once_and_only_of_what_the_run_did_not_make(tiny_object, tmp_path):
    config = build_config("test", predictor="simulated", **{"refine.iterations": 2})
    logged: list[str] = []
    with Pipeline(tiny_object, tmp_path / "run", config, progress=False, log=logged.append) as pipeline:
        pipeline.predict()
        pipeline.geometry()  # trains, asking for the predictions again
        pipeline.run_all(("full", "proj-average"))  # each asks for predict, geometry and lift again
        pipeline.geometry()
    assert not [line for line in logged if "done before" in line], logged
    logged.clear()
    with Pipeline(tiny_object, tmp_path / "run", config, progress=False, log=logged.append) as pipeline:
        pipeline.predict()
        pipeline.geometry()
        pipeline.predict()
        pipeline.run_all(("full", "proj-average"))
    said = [line for line in logged if "done before" in line]
    assert said == [
        "predict: done before, reusing materials2d/",
        "geometry: done before, reusing geometry/gaussians.ply",
        "refine [full]: done before, reusing asset/",
        "refine [proj-average]: done before, reusing asset-proj-average/",
    ], logged
