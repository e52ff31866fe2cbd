"""`benchmarks.paper_projection`: the projection of `matspray demo --preset paper` counts every stage the demo's code
runs and every variant it refines (read from the code, not listed), each term positive and labelled with what it was
measured on, and its models reduce to the figures they were fitted to."""

from __future__ import annotations

from contextlib import contextmanager

import pytest
import torch

import matspray.batch.objects as objects
from benchmarks import paper_projection as projection
from matspray.batch.demo import run_object
from matspray.method.config import build_config
from matspray.presets import DEMO_SIZES


class RecordingPipeline:
    """Stands in for `Pipeline` in `run_one_object`: records which stages the demo's code runs."""

    calls: list[str] = []

    def __init__(self, *args, **kwargs):
        self.has_maps, self.device, self.backend = True, "cpu", "torch"

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def predict(self):
        self.calls.append("predict")

    def geometry(self):
        self.calls.append("geometry")

    def refine(self, variant):
        self.calls.append(f"refine [{variant}]")


@contextmanager
def recorded_stages(monkeypatch):
    RecordingPipeline.calls = []
    monkeypatch.setattr(objects, "Pipeline", RecordingPipeline)
    monkeypatch.setattr(objects, "has_ground_truth", lambda pipeline: True)
    monkeypatch.setattr(objects, "evaluate_run", lambda *a, **k: RecordingPipeline.calls.append("eval") or {})
    monkeypatch.setattr(objects, "write_report", lambda *a, **k: None)
    yield RecordingPipeline.calls


@pytest.fixture
def cpu():
    """CPU figures of the shape `cpu_figures` measures (measured for real in the slow test below): the projection's
    coverage and labels do not depend on their values."""
    merger = {"views": [6, 100], "seconds": [0.01, 0.02], "a": 0.0094, "b": 1.06e-4, "gaussians": 2000}
    ratios = {name: 1.0 for name in projection.paper_variants() if projection.get_variant(name).trains}
    return {
        "merger": merger,
        "variant_ratios": ratios,
        "warm_ups": 2,
        "average_seconds": 0.01,
        "average_gaussians": 300,
    }


def test_the_projection_counts_every_stage_and_variant_the_demo_runs(monkeypatch, cpu):
    with recorded_stages(monkeypatch) as calls:
        run_object("data", "run", build_config("paper", predictor="simulated"), progress=False)
    assert calls[:2] == ["predict", "geometry"] and calls[-1] == "eval" and len(calls) == 2 + 5 + 1
    max_gaussians = build_config("paper").geometry.max_gaussians
    for final in (projection.H200["stretched_final_gaussians"], max_gaussians):
        terms = projection.project(cpu, final)
        names = [t.stage for t in terms]
        for stage in calls:  # each stage the demo runs has its term (refine's: one per variant)
            assert sum(name.split(" (")[0] == stage for name in names) == 1, (stage, names)
        for inside in ("lift", "frozen views", "light warm-up"):  # what refine's first variant does once
            assert any(name.startswith(inside) for name in names), inside
        for term in terms:
            assert term.seconds > 0 and ("H200" in term.source or "CPU here" in term.source), term
    size = DEMO_SIZES["paper"]
    assert f"eval ({size.test_views} test views" in names[-1] and f"lift ({size.views} views" in names[2]
    assert projection.report(terms, max_gaussians).splitlines()[-1].split()[:2] == ["TOTAL,", "PROJECTED"]


def test_the_variants_are_those_the_demo_refines(monkeypatch):
    with recorded_stages(monkeypatch) as calls:
        run_object("data", "run", build_config("paper", predictor="simulated"), progress=False)
    assert [c[len("refine [") : -1] for c in calls if c.startswith("refine")] == list(projection.paper_variants())


def test_the_geometry_model_gives_the_measured_rate_at_its_count():
    n, rate = projection.H200["rates_gaussians"], projection.H200["geometry_rate"]
    counts = torch.full((7000,), float(n), dtype=torch.float64)
    assert projection.geometry_seconds(counts) == pytest.approx(7000 / rate, rel=1e-12)
    # more Gaussians cost more, by the profile's kernel time per Gaussian
    k = projection.H200["geometry_profile_kernels_s"] / projection.H200["geometry_profile_gaussians"]
    assert projection.geometry_seconds(counts + 1000) - projection.geometry_seconds(counts) == pytest.approx(
        7000 * 1000 * k, rel=1e-9
    )


def test_the_count_curve_follows_the_schedule():
    curve = projection.count_curve(30_000, 100_000, 1_000_000, 500, 15_000)
    assert curve[0] == curve[500] == 100_000 and curve[15_000] == curve[-1] == 1_000_000
    assert curve[7750] == pytest.approx(550_000)  # half-way up the ramp


def test_the_refine_step_model_is_the_measured_step_at_its_size_and_grows_with_views(cpu):
    rates = projection.H200
    n, v = rates["rates_gaussians"], rates["rates_views"]
    measured = projection.refine_step_seconds(rates, n, v, cpu["merger"], "refine_rate")
    assert measured == pytest.approx(1 / rates["refine_rate"], rel=1e-12)
    assert projection.refine_step_seconds(rates, n, 100, cpu["merger"], "refine_rate") > measured
    assert projection.refine_step_seconds(rates, 2 * n, v, cpu["merger"], "refine_rate") > measured


@pytest.mark.slow
def test_the_cpu_figures_are_measured():
    figures = projection.cpu_figures(500, 200, short=2, long=3, merger_views=(6, 100), repeats=3)
    merger = figures["merger"]
    assert merger["seconds"][-1] > merger["seconds"][0] and merger["b"] > 0  # 100 views' inputs against 6 views'
    assert set(figures["variant_ratios"]) == {
        v for v in projection.paper_variants() if projection.get_variant(v).trains
    }
    assert all(r > 0 for r in figures["variant_ratios"].values()) and figures["variant_ratios"]["full"] == 1.0
    # the variants that learn the light, counted once per warm-up key: at least one, at most one each
    learning = [v for v in projection.paper_variants() if projection.get_variant(v).learns_light]
    assert 1 <= figures["warm_ups"] <= len(learning) and figures["average_seconds"] > 0
