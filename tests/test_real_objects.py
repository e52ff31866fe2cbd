"""The real-object benchmark sets (benchmarks/real_objects.py, benchmarks/real): the split's rule, every committed
object plain glTF that the project's reader takes whole and renders, its kind measured, its licence recorded, and the
conversion from a source file (benchmarks/convert_real.py)."""

from __future__ import annotations

import hashlib
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pygltflib")

from benchmarks.convert_real import MAX_SIDE, convert, source_digest  # noqa: E402
from benchmarks.generalise import SET_SEEDS, main, object_set  # noqa: E402
from benchmarks.real_objects import (  # noqa: E402
    METAL_AREA,
    OBJECTS,
    REAL_DIR,
    REPO_ROOT,
    RealObject,
    metal_share,
    set_files,
    set_folder,
    split,
)
from matspray.batch.demo import asset_objects  # noqa: E402
from matspray.errors import ConfigError, DataError  # noqa: E402
from matspray.gltf import PbrMaterial, Primitive, TextureRef, read_gltf, write_glb  # noqa: E402

NOTICES = REPO_ROOT / "THIRD_PARTY_NOTICES.md"
FILES = sorted(REAL_DIR.rglob("*.glb"))
HDRIS = ["city", "forest", "interior", "studio", "sunrise", "sunset"]


def test_the_split_follows_its_rule_and_the_folders_hold_exactly_it():
    sets = split()
    dev, evaluation = sets["real-dev"], sets["real-eval"]
    assert len(OBJECTS) >= 8 and len(dev) == 3 and len(evaluation) >= 5
    assert {o.name for o in dev}.isdisjoint({o.name for o in evaluation})
    assert sorted(o.name for o in dev + evaluation) == sorted(o.name for o in OBJECTS)
    for chosen in (dev, evaluation):  # metal and dielectric in each
        assert {o.kind for o in chosen} == {"metal", "dielectric"}
    assert split(tuple(reversed(OBJECTS))) == sets  # the rule does not depend on the manifest's order
    # the rule itself, written out: per kind, sorted by name, shuffled by default_rng(80); dev takes 2 metal, 1 not
    rng = np.random.default_rng(80)
    expected = []
    for kind, picks in (("dielectric", 1), ("metal", 2)):
        group = sorted(o.name for o in OBJECTS if o.kind == kind)
        expected += [group[i] for i in rng.permutation(len(group))[:picks]]
    assert sorted(expected) == [o.name for o in dev]
    for which, chosen in sets.items():  # what `matspray bench --assets FOLDER` runs is the split's set
        assert [Path(o.asset) for o in asset_objects([set_folder(which)])] == set_files(which)
        assert [f.stem for f in set_files(which)] == [o.name for o in chosen]
    assert sorted(FILES) == sorted(set_files("real-dev") + set_files("real-eval"))  # no stray file


def test_the_sets_are_within_the_size_limit():
    total = sum(f.stat().st_size for f in FILES)
    assert total <= 25 * 10**6, f"the real objects take {total / 10**6:.1f} MB (25 MB at most)"


@pytest.mark.parametrize("path", FILES, ids=[f.stem for f in FILES])
def test_each_object_is_plain_gltf_with_textured_metallic_roughness(path):
    spec = next(o for o in OBJECTS if o.name == path.stem)
    asset = read_gltf(path)
    assert asset.notes == []  # nothing the reader skips or ignores: the renderer sees the whole material
    textures = [(m.base_color_texture, m.metallic_roughness_texture) for m in asset.materials]
    assert any(base is not None for base, _ in textures) and any(mr is not None for _, mr in textures)
    for texture in (t for pair in textures for t in pair if t is not None):
        assert max(texture.image.shape[:2]) <= MAX_SIDE
    assert asset.extras["licence"] == spec.licence in ("CC0-1.0", "CC-BY-4.0")
    assert spec.repo in asset.extras["source"] and spec.commit in asset.extras["source"]
    # the kind the split used is the kind the file has
    share = metal_share(path)
    assert (share >= METAL_AREA) == (spec.kind == "metal"), f"{path.name}: metal share {share:.3f}"


def test_every_object_is_recorded_in_the_third_party_notices():
    notices = NOTICES.read_text()
    section = notices[notices.index("## Real benchmark objects") :]
    for spec in OBJECTS:
        row = next((line for line in section.splitlines() if f"/{spec.name}.glb`" in line), None)
        assert row is not None, f"{spec.name} is not in THIRD_PARTY_NOTICES.md"
        for field in (spec.title, spec.author, spec.licence, spec.repo, spec.commit[:12]):
            assert field in row, f"{spec.name}: '{field}' missing from its notice"


@pytest.mark.slow
@pytest.mark.parametrize("path", FILES, ids=[f.stem for f in FILES])
def test_each_object_renders_at_tiny_size_with_its_kind_of_material(path, tmp_path):
    pytest.importorskip("mitsuba")
    from matspray.synth import SynthConfig, make_object

    config = SynthConfig(
        asset=str(path), resolution=16, train_views=1, test_views=0, spp=4, env_height=16, gt_samples=1
    )
    make_object(config, tmp_path, progress=False)
    from PIL import Image

    photo = np.asarray(Image.open(tmp_path / "train" / "r_000.png"), dtype=np.float64) / 255.0
    metallic = np.asarray(Image.open(tmp_path / "train" / "r_000_metallic.png"), dtype=np.float64)[..., 0] / 255.0
    covered = photo[..., 3] > 0.5
    assert covered.sum() >= 16  # the object fills part of the view
    assert photo[covered, :3].max() > 0.02  # lit
    kind = next(o.kind for o in OBJECTS if o.name == path.stem)
    if kind == "metal":  # both kinds appear across the set's renders
        assert (metallic[covered] > 0.5).any()
    else:
        assert (metallic[covered] < 0.5).mean() > 0.5


def test_the_protocol_runs_the_real_sets_as_its_procedural_ones():
    dev, evaluation = object_set("real-dev", None, HDRIS), object_set("real-eval", None, HDRIS)
    assert [REPO_ROOT / o.asset for o in dev] == set_files("real-dev")
    assert [REPO_ROOT / o.asset for o in evaluation] == set_files("real-eval")
    assert [o.seed for o in dev] == [SET_SEEDS["real-dev"] + i for i in range(3)]
    assert {o.seed for o in dev + evaluation}.isdisjoint({o.seed for o in object_set("dev", 50, HDRIS)})
    assert dev[0].name == f"real-dev-00-{set_files('real-dev')[0].stem}"
    for o in dev + evaluation:
        assert o.env in HDRIS and len(set(o.relight_envs)) == 2 and o.env not in o.relight_envs
    assert object_set("real-dev", 2, HDRIS) == dev[:2]
    assert len(object_set("dev", None, HDRIS)) == 6  # a procedural set's default is unchanged
    with pytest.raises(ConfigError, match=r"--objects must be in \[1, 3\] for the set real-dev, got 4"):
        object_set("real-dev", 4, HDRIS)


def test_the_protocol_refuses_too_many_real_objects_in_one_line(capsys, tmp_path):
    assert main(["--set", "real-dev", "--objects", "4", "--preset", "test", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.strip() == "error: --objects must be in [1, 3] for the set real-dev, got 4"
    assert not (tmp_path / "objects").exists()


# ------------------------------------------------------------------------------------------ the conversion
QUAD = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float64)
FACES = np.array([[0, 1, 2], [0, 2, 3]])
UVS = QUAD[:, :2].copy()


def source_file(folder: Path) -> Path:
    """A source with a 1024 x 768 RGBA base colour, an occlusion-roughness-metallic texture, and a second primitive
    whose material is to be left out."""
    rng = np.random.default_rng(0)
    base = np.round(rng.random((768, 1024, 4)) * 255) / 255
    orm = np.round(rng.random((768, 1024, 3)) * 255) / 255
    materials = [
        PbrMaterial("kept", (0.9, 0.8, 0.7, 0.5), 1.0, 0.6, TextureRef(base), TextureRef(orm)),
        PbrMaterial("arrows", (1.0, 0.0, 0.0, 1.0), 0.0, 0.5),
    ]
    primitives = [
        Primitive("arrows", QUAD + 2.0, FACES, (UVS,), None, 1),
        Primitive("body", QUAD, FACES, (UVS,), None, 0),
    ]
    path = folder / "source.glb"
    write_glb(path, primitives, materials)
    return path


def test_conversion_shrinks_by_box_filter_drops_what_the_renderer_ignores_and_checks_the_source(tmp_path):
    source = source_file(tmp_path)
    spec = RealObject(
        "quad", "Quad", "nobody", "CC0-1.0", "a/b", "0" * 40, "source.glb", source_digest(source), "metal", ("arrows",)
    )
    out = tmp_path / "dev" / "quad.glb"
    done = convert(spec, source, out)
    assert done["primitives"] == 1 and done["textures"] == ["512x384"]
    original, converted = read_gltf(source), read_gltf(out)
    assert [p.name for p in converted.primitives] == ["body"] and converted.primitives[0].material == 0
    np.testing.assert_allclose(converted.primitives[0].positions, QUAD)
    material = converted.materials[0]
    assert material.base_color_factor == (0.9, 0.8, 0.7, 1.0)  # alpha dropped, colour factors kept
    assert (material.metallic_factor, material.roughness_factor) == (1.0, 0.6)
    base, mr = material.base_color_texture.image, material.metallic_roughness_texture.image
    assert base.shape == (384, 512, 3) and mr.shape == (384, 512, 3)
    # each texel the mean of the 2 x 2 it covers (8-bit), occlusion (R) zeroed
    source_base = original.materials[0].base_color_texture.image
    blocks = np.round(source_base[..., :3].astype(np.float64) * 255).reshape(384, 2, 512, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(base * 255, blocks, atol=0.51)
    source_mr = original.materials[0].metallic_roughness_texture.image
    blocks = np.round(source_mr.astype(np.float64) * 255).reshape(384, 2, 512, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(mr[..., 1:] * 255, blocks[..., 1:], atol=0.51)
    assert (mr[..., 0] == 0).all()
    assert converted.extras["licence"] == "CC0-1.0" and "a/b" in converted.extras["source"]
    # a source that is not the recorded one is refused in one line, and nothing is written
    with pytest.raises(DataError, match=re.escape(f"{source}: SHA-256 ")) as error:
        convert(replace(spec, source_sha256="f" * 64), source, tmp_path / "other.glb")
    assert "\n" not in str(error.value) and not (tmp_path / "other.glb").exists()


def test_the_source_digest_covers_the_files_a_gltf_refers_to(tmp_path):
    pygltflib = pytest.importorskip("pygltflib")
    glb = source_file(tmp_path)
    gltf = pygltflib.GLTF2().load(str(glb))
    gltf.convert_images(pygltflib.ImageFormat.FILE, path=str(tmp_path) + "/")
    gltf.convert_buffers(pygltflib.BufferFormat.BINFILE)
    gltf.save(str(tmp_path / "source.gltf"))
    path = tmp_path / "source.gltf"
    before = source_digest(path)
    image = next(f for f in tmp_path.iterdir() if f.suffix == ".png")
    image.write_bytes(image.read_bytes() + b"\0")
    assert source_digest(path) != before
    assert len(before) == 64 and before != hashlib.sha256(path.read_bytes()).hexdigest()
