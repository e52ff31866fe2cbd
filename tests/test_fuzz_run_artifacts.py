"""Property-based tests of the files of a run folder that later stages and commands read: the stage records
(stage.json), timings.json, config.yaml, dataset.json, geometry/gaussians.ply, materials2d/ (16-bit PNG maps and
predictor.json), lift/projected.pt, masks/masks.pt and region.json (the masks stage of a capture without masks),
asset/asset.ply, visibility.pt, history.json and envmap.exr. Each is damaged in a finished tiny run (truncated, bytes
flipped, replaced by garbage; JSON and YAML of the wrong types or with fields dropped; torch files with keys dropped,
values of the wrong type, shape or dtype, NaN or Inf; maps of another size, channel count or range) and read again
by the function the commands read it with.

A stage record that cannot be read marks no finished stage (the stage is made again). Every other reader refuses
with one line naming the file and what to do (for a stage's file: delete the stage folder and rerun), or returns
what it promises (checked: finite, the run's Gaussians and views, values in range); an intact file reads as written.
A few damaged runs go through the commands themselves: `matspray run` resuming, `eval`, `relight`, `export` and the
viewer's ViewerRun.
"""

from __future__ import annotations

import io
import json
import math
import shutil
from contextlib import contextmanager
from pathlib import Path

import pytest
import torch
import yaml
from hypothesis import event, given, settings
from hypothesis import strategies as st

from matspray.data.images import write_raw
from matspray.errors import MatsprayError
from matspray.geometry.ply import read_ply, write_ply
from matspray.geometry.region import ObjectRegion
from matspray.method.asset import CHANNELS, read_asset, read_history, write_visibility
from matspray.method.config import build_config
from matspray.method.lift import load_lift
from matspray.method.masks import ObjectMasks, read_object_masks, read_region, write_object_masks
from matspray.method.pipeline import Pipeline
from matspray.predictors import read_materials2d, read_predictor_info
from matspray.render.shade.envmap import EnvironmentMap
from matspray.rundir import RunDir, fingerprint
from tests.fuzzing import damaged
from tests.test_fuzz_images import damage
from tests.test_fuzz_transforms import FUZZ

pytest.importorskip("mitsuba")

STAGES = ("materials2d", "geometry", "lift", "asset", "masks")
# JSON values of the wrong type or out of range, as a hand edit or a damaged file leaves them
SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.sampled_from([0, -1, 1, 2**63, 0.5, -0.0, 1e308, float("nan"), float("inf"), -float("inf")]),
    st.sampled_from(["", "abc", "0123456789abcdef", "/nonexistent", "a\0b", "full", "1.5"]),
)
VALUES = st.one_of(
    SCALARS,
    st.lists(SCALARS, max_size=4),
    st.dictionaries(st.sampled_from(["fingerprint", "source", "x", "step"]), SCALARS, max_size=2),
)
GARBAGE = st.sampled_from(
    [
        b"",
        b"\0" * 32,
        b"{",
        b"[1, 2",
        b"null",
        b"\xff\xfe garbage \x80",
        b"PK\x03\x04 not a zip",
        b"ply\nformat ascii 1.0\n",
        b"- a\n- b\n",
        b"key: [unclosed",
        b"\x89PNG\r\n\x1a\n",
    ]
)
CONFIG = dict(predictor="simulated", **{"refine.iterations": 4})


def run_config():
    return build_config("test", **CONFIG)


@pytest.fixture(scope="module")
def finished_run(tiny_object, tmp_path_factory):
    """A finished tiny run (no shadow maps, as by default), with a masks stage added as a capture without masks has
    one (made from the run's own geometry and views) and a visibility.pt beside the asset. Returns (run, scene)."""
    run = tmp_path_factory.mktemp("fuzz-run") / "run"
    with Pipeline(tiny_object, run, run_config(), progress=False, log=lambda _: None) as pipeline:
        pipeline.run_all()
        scene = pipeline.scene
    count = len(read_ply(run / "geometry" / "gaussians.ply")[0])
    masks = {split: {v.name: torch.rand(v.height, v.width) for v in scene.split(split)} for split in ("train", "test")}
    write_object_masks(
        run / "masks",
        ObjectMasks(ObjectRegion(center=(0.0, 0.0, 0.0), radius=2.0), torch.ones(count, dtype=torch.bool), masks),
    )
    RunDir(run).finish_stage("masks", fingerprint("masks", "fuzz"), {}, 0.1, {"inside": count})
    write_visibility(run / "asset" / "visibility.pt", torch.rand(len(read_asset(run / "asset").gaussians), 8))
    return run, scene


@contextmanager
def damaging(path: Path):
    """Runs the block (which damages `path`), then puts back what the file held."""
    saved = path.read_bytes()
    try:
        yield path
    finally:
        path.write_bytes(saved)


def refused(read, path: Path, label: str, hint: tuple[str, ...] = ("delete", "rerun")):
    """The property of every reader here: a result, or one line naming `path` and saying what to do (one of `hint`'s
    words; () where the reader is not this task's to change)."""
    try:
        result = read()
    except MatsprayError as exc:
        message = str(exc)
        assert "\n" not in message and str(path) in message, message
        assert not hint or any(word in message for word in hint), f"says nothing to do: {message}"
        event(f"{label} refused")
        return None
    event(f"{label} accepted")
    return result


# ------------------------------------------------------------------------------------------ damage
@st.composite
def json_damage(draw, document):
    """New bytes for a JSON file: garbage, cut or flipped bytes, a value of the wrong type,
    or a field set or dropped."""
    kind = draw(st.sampled_from(["field", "field", "drop", "whole", "bytes", "garbage"]))
    blob = json.dumps(document).encode()
    if kind == "garbage":
        return draw(GARBAGE)
    if kind == "bytes":
        return damaged(blob, *draw(damage(len(blob))))
    if kind == "whole":
        return json.dumps(draw(VALUES)).encode()
    copy = json.loads(blob)
    keys = list(copy) if isinstance(copy, dict) else list(range(len(copy)))
    if not keys:
        return json.dumps(draw(VALUES)).encode()
    key = draw(st.sampled_from(keys))
    if kind == "drop":
        del copy[key]
    elif isinstance(copy[key], list) and copy[key] and draw(st.booleans()):
        copy[key][draw(st.integers(0, len(copy[key]) - 1))] = draw(VALUES)
    elif isinstance(copy[key], dict) and copy[key] and draw(st.booleans()):
        copy[key][draw(st.sampled_from(sorted(copy[key])))] = draw(VALUES)
    else:
        copy[key] = draw(VALUES)
    return json.dumps(copy).encode()


def tensor_edits():
    """A function changing one tensor: wrong dtype, shape or values."""
    return st.sampled_from(
        [
            lambda t: t.float(),
            lambda t: t.to(torch.int64),
            lambda t: t.bool(),
            lambda t: t.to(torch.uint8),
            lambda t: t[:-1],
            lambda t: t[:0],
            lambda t: t.unsqueeze(0),
            lambda t: t.reshape(-1),
            lambda t: torch.cat([t, t[:1]]),
            lambda t: t.float().fill_(float("nan")),
            lambda t: t.float() * float("inf"),
            lambda t: t.float() + 2.0,
            lambda t: -t.float(),
            lambda t: t.transpose(0, 1) if t.dim() > 1 else t.flip(0),
            lambda t: t.double(),
        ]
    )


@st.composite
def torch_damage(draw, path: Path):
    """New bytes for a torch file: garbage or cut, or its dictionary edited (a key dropped, a value of another type,
    a tensor of another dtype, shape or values), reached through nested dictionaries."""
    blob = path.read_bytes()
    kind = draw(st.sampled_from(["edit", "edit", "edit", "bytes", "garbage"]))
    if kind == "garbage":
        return draw(GARBAGE)
    if kind == "bytes":
        return damaged(blob, *draw(damage(len(blob))))
    data = torch.load(io.BytesIO(blob), weights_only=True)
    for _ in range(draw(st.integers(1, 2))):
        parent, key = data, None
        while True:  # walk down to a value
            key = draw(st.sampled_from(sorted(parent, key=str))) if isinstance(parent, dict) and parent else None
            if key is None or not isinstance(parent[key], dict) or not parent[key] or draw(st.booleans()):
                break
            parent = parent[key]
        if key is None:
            continue
        action = draw(st.sampled_from(["tensor", "tensor", "drop", "value"]))
        if action == "drop":
            del parent[key]
        elif action == "tensor" and isinstance(parent[key], torch.Tensor):
            parent[key] = draw(tensor_edits())(parent[key])
        elif action == "tensor" and isinstance(parent[key], list) and parent[key]:
            parent[key] = parent[key][:-1] if draw(st.booleans()) else [*parent[key][1:], parent[key][0]]
        else:
            parent[key] = draw(st.one_of(VALUES, st.just(torch.zeros(3)), st.just({"a": torch.zeros(2)})))
    buffer = io.BytesIO()
    torch.save(data, buffer)
    return buffer.getvalue()


def test_intact_artifacts_read_as_written(finished_run):
    run, scene = finished_run
    folder = RunDir(run)
    assert all(folder.stage_done(stage, folder.stage_fingerprint(stage), []) for stage in STAGES)
    assert set(folder.timings()) >= {"materials2d", "geometry", "lift", "asset"} and folder.dataset()[
        "train_views"
    ] == [v.name for v in scene.train]
    count = len(read_ply(run / "geometry" / "gaussians.ply")[0])
    lifted = load_lift(run / "lift" / "projected.pt", "cpu")
    assert len(lifted.kept) == count and lifted.values.shape == (int(lifted.kept.sum()), len(scene.train), 5)
    masks = read_object_masks(run / "masks")
    assert len(masks.inside) == count and set(masks.masks["test"]) == {v.name for v in scene.test}
    maps = read_materials2d(run, scene.train)
    assert all((maps[v.name].height, maps[v.name].width) == (v.height, v.width) for v in scene.train)
    asset = read_asset(run / "asset")
    assert (
        asset.visibility is not None
        and asset.visibility.shape == (len(asset.gaussians), 8)
        and read_history(run / "asset")
    )


# ---------------------------------------------------------------------------------- stage records and JSON/YAML records
@settings(FUZZ, max_examples=40)
@given(stage=st.sampled_from(STAGES), data=st.data())
def test_damaged_stage_record_is_no_finished_stage(finished_run, stage, data):
    run, _ = finished_run
    with damaging(run / stage / "stage.json") as path:
        record = json.loads(path.read_text())
        blob = data.draw(json_damage(record))
        path.write_bytes(blob)
        done = RunDir(run).stage_done(stage, record["fingerprint"], [])
    try:
        parsed = json.loads(blob)
    except ValueError:
        parsed = None
    assert done is (isinstance(parsed, dict) and parsed.get("fingerprint") == record["fingerprint"]), (blob[:80], done)
    event(f"stage {'kept' if done else 'made again'}")


@settings(FUZZ, max_examples=20)
@given(data=st.data())
def test_damaged_timings(finished_run, data):
    run, _ = finished_run
    with damaging(run / "timings.json") as path:
        path.write_bytes(data.draw(json_damage(json.loads(path.read_text()))))
        timings = refused(lambda: RunDir(run).timings(), path, "timings")
        if timings is not None:
            assert all(isinstance(k, str) and math.isfinite(v) and v >= 0 for k, v in timings.items())
        RunDir(run).record_timing("relight", 1.5)  # a stage made again records its time: a damaged record is replaced
        assert RunDir(run).timings()["relight"] == 1.5


@settings(FUZZ, max_examples=20)
@given(data=st.data())
def test_damaged_config_yaml(finished_run, data):
    run, _ = finished_run
    with damaging(run / "config.yaml") as path:
        blob = path.read_bytes()
        config = yaml.safe_load(blob)
        kind = data.draw(st.sampled_from(["downscale", "field", "bytes", "garbage"]))
        if kind in ("downscale", "field"):
            config["downscale" if kind == "downscale" else data.draw(st.sampled_from(sorted(config)))] = data.draw(
                VALUES
            )
            blob = yaml.safe_dump(config).encode()
        else:
            blob = damaged(blob, *data.draw(damage(len(blob)))) if kind == "bytes" else data.draw(GARBAGE)
        path.write_bytes(blob)
        read = refused(lambda: RunDir(run).config(), path, "config", hint=("restore", "rerun", "set"))
        if read is not None:
            assert isinstance(read, dict)
            downscale = refused(lambda: RunDir(run).downscale(), path, "downscale", hint=("set",))
            assert downscale is None or 0 < downscale < math.inf


@settings(FUZZ, max_examples=25)
@given(data=st.data())
def test_damaged_dataset_record(finished_run, data):
    run, _ = finished_run
    with damaging(run / "dataset.json") as path:
        identity = json.loads(path.read_text())
        path.write_bytes(data.draw(json_damage(identity)))
        read = refused(lambda: RunDir(run).dataset(), path, "dataset", hint=("--overwrite",))
        if read is not None:
            assert isinstance(read["source"], str) and all(
                isinstance(n, str) for n in read.get("train_views", []) + read.get("test_views", [])
            )
        # a record of another dataset is refused naming the run folder; one that cannot be read, naming the record
        if refused(lambda: RunDir(run).claim(identity), run, "claim", hint=("overwrit", "new run folder")) is not None:
            assert json.loads(path.read_text()) == identity  # claimed: the record is this dataset's


# ------------------------------------------------------------------------------------------ Gaussians and the asset
@st.composite
def ply_damage(draw, path: Path):
    """New bytes for a PLY file: cut, flipped, garbage, or NaN/Inf/zero quaternions written into it."""
    kind = draw(st.sampled_from(["bytes", "bytes", "values", "garbage"]))
    blob = path.read_bytes()
    if kind == "garbage":
        return draw(GARBAGE)
    if kind == "bytes":
        return damaged(blob, *draw(damage(len(blob))))
    materials = CHANNELS if path.name == "asset.ply" else ()
    gaussians, normals, *extra = read_ply(path, extra=materials)
    extra = extra[0] if extra else {}
    field = draw(st.sampled_from(["means", "quats", "sh", "normals", *(["roughness"] if extra else [])]))
    tensor = normals if field == "normals" else extra[field] if field == "roughness" else getattr(gaussians, field)
    tensor.view(-1)[draw(st.integers(0, tensor.numel() - 1))] = draw(
        st.sampled_from([float("nan"), float("inf"), -float("inf")])
    )
    if field == "quats":
        gaussians.quats[draw(st.integers(0, len(gaussians) - 1))] = 0.0
    out = path.with_name(".damaged.ply")
    write_ply(out, gaussians, normals, extra=extra)
    blob = out.read_bytes()
    out.unlink()
    return blob


def check_finite_gaussians(gaussians) -> None:
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        assert torch.isfinite(getattr(gaussians, name)).all()
    assert (gaussians.quats.double().norm(dim=-1) > 0).all()


@settings(FUZZ, max_examples=20)
@given(data=st.data())
def test_damaged_geometry_ply(finished_run, data):
    run, _ = finished_run
    with damaging(run / "geometry" / "gaussians.ply") as path:
        intact = read_ply(path)[0]
        blob = data.draw(ply_damage(path))
        path.write_bytes(blob)
        read = refused(lambda: read_ply(path), path, "geometry")
    if read is not None:  # a flipped byte inside a value may leave a readable file
        check_finite_gaussians(read[0])
        assert len(read[0]) == len(intact)


@settings(FUZZ, max_examples=25)
@given(data=st.data())
def test_damaged_asset(finished_run, data):
    run, _ = finished_run
    folder = run / "asset"
    which = data.draw(st.sampled_from(["asset.ply", "asset.ply", "visibility.pt"]))
    with damaging(folder / which) as path:
        count = len(read_asset(folder).gaussians)
        path.write_bytes(data.draw(ply_damage(path) if which == "asset.ply" else torch_damage(path)))
        asset = refused(lambda: read_asset(folder), path, "asset", hint=("delete", "rerun"))
    if asset is not None:
        check_finite_gaussians(asset.gaussians)
        assert (
            len(asset.gaussians) == count
            and torch.isfinite(asset.materials).all()
            and torch.isfinite(asset.normals).all()
        )
        if asset.visibility is not None:
            assert (
                asset.visibility.shape[0] == count
                and 0 <= float(asset.visibility.min()) <= float(asset.visibility.max()) <= 1
            )


@settings(FUZZ, max_examples=15)
@given(data=st.data())
def test_damaged_history_and_envmap(finished_run, data):
    run, _ = finished_run
    which = data.draw(st.sampled_from(["history.json", "envmap.exr"]))
    with damaging(run / "asset" / which) as path:
        blob = path.read_bytes()
        if which == "history.json":
            path.write_bytes(data.draw(json_damage(json.loads(blob))))
            history = refused(lambda: read_history(run / "asset"), path, "history")
            assert history is None or all(isinstance(r, dict) and math.isfinite(r["step"]) for r in history)
        else:  # read by matspray.render.shade.envmap (fuzzed alone in tests/test_fuzz_envmaps.py): one line naming it
            path.write_bytes(data.draw(st.one_of(GARBAGE, damage(len(blob)).map(lambda d: damaged(blob, *d)))))
            env = refused(lambda: EnvironmentMap.from_file(path), path, "envmap", hint=())
            assert env is None or (torch.isfinite(env.map).all() and env.map.shape[1] == 2 * env.map.shape[0])


# ------------------------------------------------------------------------------------------ lift, masks, 2D maps
@settings(FUZZ, max_examples=40)
@given(data=st.data())
def test_damaged_lift(finished_run, data):
    run, scene = finished_run
    with damaging(run / "lift" / "projected.pt") as path:
        path.write_bytes(data.draw(torch_damage(path)))
        lifted = refused(lambda: load_lift(path, "cpu"), path, "lift")
    if lifted is not None:
        count, views = int(lifted.kept.sum()), len(scene.train)
        assert len(lifted.kept) == len(
            read_ply(run / "geometry" / "gaussians.ply")[0]
        )  # the masks stage holds every Gaussian
        assert lifted.values.shape == (count, views, 5) and lifted.seen.shape == (count, views)
        assert torch.isfinite(lifted.values).all() and lifted.view_names == [v.name for v in scene.train]


@settings(FUZZ, max_examples=40)
@given(data=st.data())
def test_damaged_object_masks(finished_run, data):
    run, scene = finished_run
    which = data.draw(st.sampled_from(["masks.pt", "masks.pt", "region.json"]))
    with damaging(run / "masks" / which) as path:
        damage_of = torch_damage(path) if which == "masks.pt" else json_damage(json.loads(path.read_text()))
        path.write_bytes(data.draw(damage_of))
        masks = refused(lambda: read_object_masks(run / "masks"), path, "masks")
        region = refused(lambda: read_region(run / "masks"), run / "masks" / "region.json", "region")
    if masks is not None:
        assert len(masks.inside) == len(read_ply(run / "geometry" / "gaussians.ply")[0]) and masks.inside.any()
        alphas = [view.alpha for view in scene.views]
        try:  # what the pipeline does with them: every view's alpha, the region's box as the bounds
            applied = refused(lambda: masks.apply(scene), run / "masks" / "masks.pt", "apply")
            if applied is None:
                for view in scene.views:
                    assert (
                        view.alpha.shape == (view.height, view.width)
                        and 0 <= float(view.alpha.min()) <= float(view.alpha.max()) <= 1
                    )
        finally:
            for view, alpha in zip(scene.views, alphas):
                view.alpha = alpha
    if region is not None:
        assert torch.isfinite(region.bounds()).all() and region.describe()


@st.composite
def map_damage(draw, path: Path):
    """New bytes for a 16-bit PNG map: cut, flipped, garbage, or a decodable map of another size,
    channel count or depth."""
    kind = draw(st.sampled_from(["bytes", "bytes", "garbage", "other map"]))
    blob = path.read_bytes()
    if kind == "garbage":
        return draw(GARBAGE)
    if kind == "bytes":
        return damaged(blob, *draw(damage(len(blob))))
    height, width = draw(st.sampled_from([(32, 32), (16, 32), (1, 1)]))
    channels, bits = draw(st.sampled_from([1, 2, 3, 4])), draw(st.sampled_from([8, 16]))
    out = path.with_name(".damaged.png")
    write_raw(out, torch.rand(height, width, channels), bits=bits)
    blob = out.read_bytes()
    out.unlink()
    return blob


@settings(FUZZ, max_examples=35)
@given(data=st.data())
def test_damaged_materials2d(finished_run, data):
    run, scene = finished_run
    folder = run / "materials2d"
    if data.draw(st.sampled_from([False, False, False, True])):  # predictor.json, which eval's report reads
        with damaging(folder / "predictor.json") as path:
            path.write_bytes(data.draw(json_damage(json.loads(path.read_text()))))
            info = refused(lambda: read_predictor_info(run), path, "predictor.json", hint=("rerun",))
        assert info is None or isinstance(info, dict)
        return
    view = data.draw(st.sampled_from([v.name for v in scene.train]))
    with damaging(folder / f"{view}_{data.draw(st.sampled_from(['basecolor', 'roughness', 'metallic']))}.png") as path:
        path.write_bytes(data.draw(map_damage(path)))
        maps = refused(lambda: read_materials2d(run, scene.train), path, "materials2d")
    if maps is not None:
        for v in scene.train:
            maps[v.name].validate(v.name)
            assert (maps[v.name].height, maps[v.name].width) == (v.height, v.width)


# ------------------------------------------------------------------------------------------ the commands
def copy_of(finished_run, tmp_path: Path) -> Path:
    run, _ = finished_run
    copy = tmp_path / "run"
    shutil.copytree(run, copy, ignore=shutil.ignore_patterns("run.lock"))
    return copy


def one_line_error(capsys, named: Path, *words: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(named) in err[0] and all(w in err[0] for w in words), err
    return err[0]


def run_args(data: Path, run: Path) -> list[str]:  # the settings of the finished run (run_config)
    return [
        "run",
        "--data",
        str(data),
        "--out",
        str(run),
        "--preset",
        "test",
        "--predictor",
        "simulated",
        "--set",
        "refine.iterations=4",
    ]


def test_run_makes_a_stage_with_a_damaged_record_again(finished_run, tiny_object, tmp_path, capsys):
    """`matspray run` resuming: the asset's stage.json garbage and timings.json cut: the asset is refined again (the
    lift reused), both records written anew."""
    from matspray.cli import main

    run = copy_of(finished_run, tmp_path)
    (run / "asset" / "stage.json").write_bytes(b"\x00garbage")
    (run / "timings.json").write_text('{"geometry": 1.')
    assert main(run_args(tiny_object, run)) == 0
    out = capsys.readouterr().out
    assert "reusing lift/projected.pt" in out and "reusing asset/" not in out, out
    assert json.loads((run / "asset" / "stage.json").read_text())["fingerprint"] and RunDir(run).timings()["asset"] >= 0


def test_run_names_a_damaged_lift_it_has_to_read(finished_run, tiny_object, tmp_path, capsys):
    """`matspray run` resuming where the asset is to be made again and lift/projected.pt is cut: one line naming the
    file and the stage folder to delete; nothing refined from it."""
    from matspray.cli import main

    run = copy_of(finished_run, tmp_path)
    (run / "asset" / "stage.json").unlink()
    lift = run / "lift" / "projected.pt"
    lift.write_bytes(lift.read_bytes()[:300])
    assert main(run_args(tiny_object, run)) == 2
    one_line_error(capsys, lift, f"delete {run / 'lift'} and rerun `matspray run`")
    assert not (run / "asset" / "stage.json").exists()


@pytest.mark.parametrize("command", ["relight", "export", "eval", "view"])
def test_commands_name_the_damaged_file_they_read(finished_run, tmp_path, capsys, command):
    """relight on a cut asset.ply, export on a damaged region.json, eval on a garbage dataset.json, the viewer on an
    asset.ply with NaN in it: one line naming the file and what to do."""
    from matspray.cli import main

    run = copy_of(finished_run, tmp_path)
    if command == "relight":
        asset = run / "asset" / "asset.ply"
        asset.write_bytes(asset.read_bytes()[:-100])
        assert main(["relight", "--run", str(run), "--env", "studio", "--out", str(tmp_path / "relit")]) == 2
        one_line_error(capsys, asset, f"delete {run / 'asset'}")
        assert not (tmp_path / "relit").exists()
    elif command == "export":
        (run / "masks" / "region.json").write_text('{"center": [0, 0], "radius": -1}')
        assert main(["export", "--run", str(run), "--out", str(tmp_path / "mesh.glb")]) == 2
        one_line_error(capsys, run / "masks" / "region.json", f"delete {run / 'masks'}")
        assert not (tmp_path / "mesh.glb").exists()
    elif command == "eval":
        (run / "dataset.json").write_text("[]")
        assert main(["eval", "--run", str(run)]) == 2
        one_line_error(capsys, run / "dataset.json", "--overwrite")
    else:
        from matspray.view.scene import ViewerRun

        asset = run / "asset" / "asset.ply"
        gaussians, normals, extra = read_ply(asset, extra=CHANNELS)
        gaussians.means[0, 0] = float("nan")
        write_ply(asset, gaussians, normals, extra=extra)
        with pytest.raises(MatsprayError) as refusal:
            ViewerRun(run, notify=lambda _: None).asset("full")
        message = str(refusal.value)
        assert "\n" not in message and str(asset) in message and f"delete {run / 'asset'}" in message
