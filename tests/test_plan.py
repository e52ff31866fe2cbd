"""Resolve, then run: `resolve_plan` turns the config and the scene into each stage's settings and fingerprint without
touching a run folder; `Pipeline` holds that plan (it is not one), resolves it once and completes it once, when the
2D maps' normals are known; the fingerprints it records are the plan's."""

from __future__ import annotations

from collections import Counter

import pytest
import torch

from matspray.method import pipeline as pipeline_module
from matspray.method import plan as plan_module
from matspray.method.config import build_config
from matspray.method.pipeline import Pipeline
from matspray.method.plan import RunPlan, open_scene, resolve_plan, with_normals
from matspray.rundir import RunDir


def config():
    return build_config("test", predictor="simulated", **{"refine.iterations": 2, "geometry.iterations": 6})


def test_the_plan_is_a_function_of_the_config_and_the_scene(tiny_object, tmp_path):
    resolved, scene = open_scene(tiny_object, config(), log=lambda _: None)
    cpu = torch.device("cpu")
    first = resolve_plan(resolved, scene, cpu)
    assert first == resolve_plan(resolved, scene, cpu)  # the same inputs, the same plan
    # a masked object whose geometry trains on the predicted normals waits on the predictions for all but predict
    assert not first.complete and first.geometry is None and first.lift is None and first.refine is None
    with_maps_normals, without = with_normals(first, True), with_normals(first, False)
    assert with_maps_normals.geometry.settings.predicted_normal_weight == 1.0
    assert without.geometry.settings.predicted_normal_weight == 0.0
    assert with_maps_normals.geometry.fingerprint != without.geometry.fingerprint
    assert with_maps_normals.predict == without.predict == first.predict  # predict never follows them
    assert with_maps_normals.refine["full"].settings.predicted_normal_weight == 1.0
    assert with_maps_normals.refine["no-prior"].settings.predicted_normal_weight == 0.0  # reads no 2D maps
    assert with_normals(with_maps_normals, False) is with_maps_normals  # complete: resolved once
    assert not any(tmp_path.iterdir())  # no run folder: nothing read or written


@pytest.mark.slow  # about 10 s: a whole (tiny) run
def test_the_pipeline_holds_its_plan_resolves_it_once_and_records_its_fingerprints(tiny_object, tmp_path, monkeypatch):
    assert not issubclass(Pipeline, RunPlan)
    calls = Counter()

    def counted(name, function):
        def wrapper(*args, **kwargs):
            calls[name] += 1
            return function(*args, **kwargs)

        return wrapper

    monkeypatch.setattr(plan_module, "resolve_plan", counted("resolve_plan", plan_module.resolve_plan))
    monkeypatch.setattr(pipeline_module, "with_normals", counted("with_normals", pipeline_module.with_normals))
    run = tmp_path / "run"
    with Pipeline(tiny_object, run, config(), progress=False, log=lambda _: None) as pipeline:
        pipeline.run_all(["proj-average"])  # no training: the stages before it are the point
        held = pipeline.plan
    assert calls == {"resolve_plan": 1, "with_normals": 1}  # resolved before any stage, completed after predict
    assert held.complete and held.normals is True
    resolved, scene = open_scene(tiny_object, config(), log=lambda _: None)
    again = with_normals(resolve_plan(resolved, scene, pipeline.device), True)
    recorded = RunDir(run)
    assert recorded.stage_fingerprint("materials2d") == again.predict.fingerprint
    assert recorded.stage_fingerprint("geometry") == again.geometry.fingerprint
    assert recorded.stage_fingerprint("lift") == again.lift.fingerprint
    assert recorded.stage_fingerprint("asset-proj-average") == again.refine["proj-average"].fingerprint
    calls.clear()
    with Pipeline(tiny_object, run, config(), progress=False, log=lambda _: None) as resumed:  # a run made before
        assert resumed.plan == held  # complete from the start: the normals as the predictions recorded them
        resumed.run_all(["proj-average"])
    assert calls == {"resolve_plan": 1}
