"""Property-based tests of reading a run folder's config.yaml back (`RunDir.config`, `RunDir.downscale`, which
eval, relight, report and export load the scene with): the file `write_config` writes, with a top-level value
replaced (by a wrong type, NaN, Inf, zero, negative, YAML syntax), the whole document replaced, then truncated at
any character or with random bytes flipped.

Each reader refuses with a one-line MatsprayError naming config.yaml, or returns a mapping and a finite downscale
> 0; an intact file gives back the downscale written.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from matspray.method.config import PipelineConfig
from matspray.rundir import RunDir
from tests.fuzzing import damaged, read_or_refuse
from tests.test_fuzz_images import damage
from tests.test_fuzz_transforms import FUZZ

KEYS = st.sampled_from(["downscale", "predictor", "predictor_options", "preset", "geometry", "seed"])
VALUES = st.sampled_from(
    [
        "null",
        "~",
        ".nan",
        ".inf",
        "-.inf",
        "0",
        "-1",
        "0.0",
        "1e400",
        "99999999999999999999999999",
        "true",
        "'2'",
        "two",
        "[1, 2]",
        "{a: 1}",
        "",
        "[",
        "{",
        "'",
        '"',
        "!!python/object:os.system x",
        "&a 1",
        "*b",
        "1 # c",
        "- 1",
        "0x10",
        "1_0",
        "2020-01-01",
        "!!binary aGk=",
        "|\n  text",
    ]
)
DOCUMENTS = st.sampled_from(
    ["", "null", "[]", "- 1\n- 2", "3", "text", "---\n---\na: 1", "\t", "a: 1\na: 2", "\x00", "\ufeffa: 1"]
)


@pytest.fixture(scope="module")
def run():
    run = RunDir(Path(tempfile.mkdtemp(prefix="fuzz-config-")))
    run.write_config(PipelineConfig(downscale=2.0))
    return run, run.path("config.yaml").read_text()


def replace_value(text: str, key: str, value: str) -> str:
    """`text` with the top-level `key: ...` line's value replaced by `value` (YAML source)."""
    return "\n".join(f"{key}: {value}" if line.startswith(f"{key}:") else line for line in text.split("\n"))


@FUZZ
@given(edit=st.one_of(st.none(), st.tuples(KEYS, VALUES), DOCUMENTS), data=st.data())
def test_run_config(run, edit, data):
    run, intact = run
    text = intact if edit is None else edit if isinstance(edit, str) else replace_value(intact, *edit)
    blob = text.encode()
    cut, flips = data.draw(st.one_of(st.just((None, [])), damage(len(blob)))) if blob else (None, [])
    path = run.path("config.yaml")
    path.write_bytes(damaged(blob, cut, flips))
    config = read_or_refuse(run.config, path, "config ")
    downscale = read_or_refuse(run.downscale, path, "downscale ")
    if config is not None:
        assert isinstance(config, dict)
    if downscale is not None:
        assert isinstance(downscale, float) and 0 < downscale < float("inf")
    if edit is None and cut is None and not flips:
        assert downscale == 2.0 and config["predictor"] == "simulated"


@pytest.mark.parametrize(
    "predictor, options", [(["simulated"], {}), ("simulated", ["seed"]), ("simulated", {"colour": 1})]
)
def test_eval_says_what_it_cannot_read_of_a_config_predictor(tmp_path, predictor, options):
    from matspray.eval.run_eval import predict_test_views

    (tmp_path / "config.yaml").write_text(yaml.safe_dump({"predictor": predictor, "predictor_options": options}))
    predictions, note = predict_test_views(tmp_path, [])
    assert (
        predictions is None
        and note.startswith("raw 2D predictions of test views not evaluated (")
        and "config.yaml" in note
    )
