"""Predictors that declare themselves (`matspray.predictors.kinds`): the spec parsed once, the declarations read
without torch, and a toy predictor registered from this module, which the help then shows and `run` uses."""

import json
import subprocess
import sys
from dataclasses import dataclass

import pytest
import torch

from matspray.cli import build_parser, main
from matspray.data import load_scene
from matspray.errors import SettingError
from matspray.predictors import PredictorOptions, PredictorSpec, make_predictor
from matspray.predictors.base import Predictor
from matspray.predictors.kinds import PredictorKind, predictor_kinds, register, setting, unregister
from matspray.predictors.maps import MaterialMaps, read_materials2d


@pytest.mark.parametrize(
    "text, kind, argument",
    [
        ("files:outputs/dr", "files", "outputs/dr"),
        (" Simulated : harsh ", "simulated", "harsh"),
        ("marigold", "marigold", ""),
        ("files:C:/maps", "files", "C:/maps"),  # only the first ':' splits
    ],
)
def test_a_spec_is_parsed_once_into_kind_and_argument(text, kind, argument):
    assert PredictorSpec.parse(text) == PredictorSpec(kind, argument)


def test_the_declarations_load_without_torch():
    code = (
        "import sys; from matspray.predictors.kinds import predictor_kinds; kinds = predictor_kinds(); "
        "print(sorted(kinds), 'torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['files', 'ground-truth', 'marigold', 'simulated'] False"


# ------------------------------------------------------------------------------------------ a toy predictor
class ToyPredictor(Predictor):
    """Uniform maps: base colour and roughness `level`, metallic 0."""

    name = "toy"

    def __init__(self, level: float):
        self.level = level

    def predict(self, views):
        def maps(view):
            grey = torch.full((view.height, view.width), self.level)
            return MaterialMaps(grey[..., None].expand(-1, -1, 3).clone(), grey.clone(), torch.zeros_like(grey))

        return {view.name: maps(view) for view in views}

    def describe(self) -> dict:
        return {**super().describe(), "level": self.level}


@dataclass(frozen=True)
class ToyOptions:
    toy_level: float | None = setting("grey level of the toy's maps (default 0.5)", float)


TOY = PredictorKind(
    "toy",
    "toy (uniform grey maps, a test's)",
    ToyOptions,
    lambda argument, options, notify: ToyPredictor(0.5 if options.toy_level is None else options.toy_level),
    run_flags=("toy_level",),
)


@pytest.fixture
def toy():
    register(TOY)
    yield TOY
    unregister(TOY.name)


def help_of(command: str) -> str:
    parser = build_parser()
    subparsers = next(a for a in parser._actions if a.dest == "command")
    return subparsers.choices[command].format_help()


def test_a_registered_predictor_shows_in_the_help_of_predict_and_run(toy):
    for command in ("predict", "run"):
        text = " ".join(help_of(command).split())
        assert "toy (uniform grey maps, a test's)" in text and "--toy-level" in text, command
        assert "grey level of the toy's maps (default 0.5)" in text
    assert "toy" in predictor_kinds()


def test_a_registered_predictor_is_made_with_its_options_and_refuses_others(toy):
    assert make_predictor("toy", PredictorOptions(toy_level=0.25)).level == 0.25
    with pytest.raises(SettingError, match="severity: does not apply to the toy predictor"):
        make_predictor("toy", PredictorOptions(severity=1.0))
    with pytest.raises(SettingError, match="toy takes no ':' argument"):
        make_predictor("toy:x")
    unregister("toy")
    with pytest.raises(SettingError, match="unknown predictor 'toy'"):
        make_predictor("toy")


@pytest.mark.slow  # a whole run at the test preset (about 20 s)
def test_run_uses_a_registered_predictor(toy, tiny_object, tmp_path):
    out = tmp_path / "run"
    argv = ["run", "--data", str(tiny_object), "--out", str(out), "--predictor", "toy", "--toy-level", "0.25"]
    assert main([*argv, "--preset", "test", "--variant", "proj-average", "--device", "cpu"]) == 0
    info = json.loads((out / "materials2d" / "predictor.json").read_text())
    assert info["predictor"] == "toy" and info["level"] == 0.25
    maps = read_materials2d(out, load_scene(tiny_object).train)
    assert len(maps) == 6 and all(abs(float(m.roughness.mean()) - 0.25) < 1e-2 for m in maps.values())
