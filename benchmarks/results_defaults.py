"""A published pass tied to the defaults it measured. `benchmarks.generalise` records, in each results file, the
fingerprint of every default of its preset for both methods (`matspray.method.config.defaults_fingerprint`) and the
settings behind it. The evaluation set is run once, on the final defaults: when a default changes later, its figures
describe code that no longer runs by default, and `stale_defaults` names what changed, so that the evaluation is run
again rather than the figures kept (tests/test_results_defaults.py)."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.generalise_sets import EVAL_SETS
from matspray.method.config import default_settings
from matspray.presets import METHODS
from matspray.rundir import fingerprint


def flat(settings: dict, prefix: str = "") -> dict:
    """{"refine": {"iterations": 1}} -> {"refine.iterations": 1}"""
    out = {}
    for key, value in settings.items():
        name = f"{prefix}{key}"
        out.update(flat(value, name + ".") if isinstance(value, dict) and value else {name: value})
    return out


def stale_defaults(settings: dict) -> dict[str, list[str]]:
    """{method: what differs} between the defaults a pass recorded (its `settings`) and today's, for the method the
    pass ran (both where it names none); empty when they agree. What differs: each setting changed, added or gone, or
    `fingerprint` alone when the pass recorded no settings to compare with."""
    recorded = settings.get("defaults") or {}
    stale = {}
    for method in [settings["method"]] if settings.get("method") in METHODS else METHODS:
        today = default_settings(settings["preset"], method)
        if recorded.get(method) == fingerprint(today):
            continue
        before = (settings.get("default_settings") or {}).get(method)
        if before is None:
            stale[method] = ["fingerprint"]
            continue
        now, then = flat(today), flat(before)
        stale[method] = sorted(k for k in now.keys() | then.keys() if now.get(k, "<absent>") != then.get(k, "<absent>"))
    return stale


def evaluation_files(results_dir: Path) -> list[Path]:
    """The results files of an evaluation set's passes in `results_dir`."""
    files = sorted(Path(results_dir).glob("generalise-*.json"))
    return [p for p in files if json.loads(p.read_text())["settings"].get("set") in EVAL_SETS]
