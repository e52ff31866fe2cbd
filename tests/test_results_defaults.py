"""The evaluation set is run once, on the final defaults: each published pass over it is tied to the defaults it
measured, and a later change of a default fails here until the evaluation is run again."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

from benchmarks.results_defaults import evaluation_files, flat, stale_defaults
from matspray.method.config import default_settings, defaults_fingerprint

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"


def recorded(preset: str = "test") -> dict:
    """The settings block `benchmarks.generalise` writes, for a pass made on today's defaults."""
    methods = ("matspray", "paper")
    return {
        "set": "real-eval",
        "preset": preset,
        "defaults": {m: defaults_fingerprint(preset, m) for m in methods},
        "default_settings": {m: default_settings(preset, m) for m in methods},
    }


def test_a_pass_on_todays_defaults_is_current():
    assert stale_defaults(recorded()) == {}


def test_a_changed_default_is_named_for_the_method_it_changed():
    settings = recorded()
    before = copy.deepcopy(settings)
    before["default_settings"]["paper"]["refine"]["iterations"] += 1  # the pass ran with another default
    before["defaults"]["paper"] = "0" * 16
    assert stale_defaults(before) == {"paper": ["refine.iterations"]}
    before["default_settings"]["paper"]["refine"]["a_setting_gone_since"] = 1.0
    assert stale_defaults(before) == {"paper": ["refine.a_setting_gone_since", "refine.iterations"]}
    del before["default_settings"]["paper"]  # a pass that recorded only the fingerprint
    assert stale_defaults(before) == {"paper": ["fingerprint"]}
    assert stale_defaults(settings) == {}


def test_a_pass_is_tied_to_the_defaults_of_the_method_it_ran():
    settings = recorded()
    settings["default_settings"]["paper"]["refine"]["iterations"] += 1  # paper's defaults changed since the pass
    settings["defaults"]["paper"] = "0" * 16
    assert stale_defaults({**settings, "method": "matspray"}) == {}  # a pass of the default method measured none
    assert stale_defaults({**settings, "method": "paper"}) == {"paper": ["refine.iterations"]}
    assert stale_defaults(settings) == {"paper": ["refine.iterations"]}  # a pass that names no method: both


def test_flat_names_every_setting_by_its_dotted_path():
    assert flat({"a": 1, "b": {"c": 2, "d": {"e": None}}, "f": {}}) == {"a": 1, "b.c": 2, "b.d.e": None, "f": {}}
    assert "refine.iterations" in flat(default_settings("test"))


@pytest.mark.parametrize("path", evaluation_files(RESULTS), ids=lambda p: p.name)
def test_every_published_evaluation_pass_measured_todays_defaults(path):
    settings = json.loads(path.read_text())["settings"]
    assert stale_defaults(settings) == {}, (
        f"{path.name} measured other defaults than today's (settings changed since, per method: "
        f"{stale_defaults(settings)}): run the evaluation set again on these defaults and publish what comes out"
    )
