"""matspray.gltf: write_glb / read_gltf round trips, hand-built .gltf files, and bad files rejected."""

from __future__ import annotations

import base64
import json
import math

import numpy as np
import pytest

pytest.importorskip("pygltflib")

from matspray.errors import DataError  # noqa: E402
from matspray.gltf import GltfAsset, PbrMaterial, Primitive, TextureRef, TextureTransform, read_gltf, write_glb  # noqa: E402
from matspray.gltf.write import png_bytes  # noqa: E402

QUAD_POSITIONS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float64)
QUAD_UVS = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64)
QUAD_FACES = np.array([[0, 1, 2], [0, 2, 3]])


def quantised(image: np.ndarray) -> np.ndarray:
    return np.round(image * 255) / 255


def test_write_read_round_trip_keeps_meshes_materials_textures_and_extras(tmp_path):
    rng = np.random.default_rng(0)
    colour = quantised(rng.uniform(size=(4, 6, 3)))
    packed = quantised(rng.uniform(size=(3, 5, 3)))
    normals = np.tile([0.0, 0.0, 1.0], (4, 1))
    primitives = [
        Primitive("quad", QUAD_POSITIONS, QUAD_FACES, (QUAD_UVS, 1 - QUAD_UVS), normals, 0),
        Primitive("plain", QUAD_POSITIONS + 2, QUAD_FACES, (), None, 1),
        Primitive("default", QUAD_POSITIONS - 2, QUAD_FACES, (), None, None),
    ]
    materials = [
        PbrMaterial(
            "textured",
            (1.0, 0.5, 0.25, 1.0),
            0.3,
            0.7,
            TextureRef(colour, 1, TextureTransform((0.1, 0.2), 0.3, (2.0, 3.0)), "clamp", "mirror"),
            TextureRef(packed, 0, TextureTransform(), "repeat", "clamp"),
        ),
        PbrMaterial("factors", (0.2, 0.3, 0.4, 1.0), 1.0, 0.25),
    ]
    path = tmp_path / "round.glb"
    write_glb(path, primitives, materials, extras={"kind": "test", "n": 3})
    asset = read_gltf(path)
    assert isinstance(asset, GltfAsset) and asset.extras == {"kind": "test", "n": 3} and asset.notes == []
    assert [p.name for p in asset.primitives] == ["quad", "plain", "default"]
    for read, written in zip(asset.primitives, primitives):
        np.testing.assert_allclose(read.positions, written.positions, atol=1e-6)
        np.testing.assert_array_equal(read.indices, written.indices)
        assert len(read.uvs) == len(written.uvs) and read.material == written.material
        for a, b in zip(read.uvs, written.uvs):
            np.testing.assert_allclose(a, b, atol=1e-7)
    np.testing.assert_allclose(asset.primitives[0].normals, normals, atol=1e-7)
    assert asset.primitives[1].normals is None
    textured, factors = asset.materials
    assert textured.name == "textured" and textured.base_color_factor == pytest.approx((1.0, 0.5, 0.25, 1.0))
    assert (textured.metallic_factor, textured.roughness_factor) == pytest.approx((0.3, 0.7))
    base, mr = textured.base_color_texture, textured.metallic_roughness_texture
    np.testing.assert_allclose(base.image, colour, atol=1e-6)
    np.testing.assert_allclose(mr.image, packed, atol=1e-6)
    assert (base.tex_coord, base.wrap_s, base.wrap_t) == (1, "clamp", "mirror")
    assert (mr.tex_coord, mr.wrap_s, mr.wrap_t) == (0, "repeat", "clamp")
    assert base.transform == TextureTransform((0.1, 0.2), 0.3, (2.0, 3.0)) and mr.transform.is_identity()
    assert factors.base_color_texture is None and factors.roughness_factor == pytest.approx(0.25)
    assert asset.material_of(asset.primitives[2]) == PbrMaterial()
    assert not list(tmp_path.glob(".*tmp*"))


def test_texture_transform_matrix_is_the_extensions_definition():
    t = TextureTransform((0.5, -0.25), math.pi / 2, (2.0, 3.0))
    # scale, then rotate by +90 degrees as the extension defines it (u, v) -> (v, -u), then offset
    u, v = 0.3, 0.1
    expected = (0.5 + 3.0 * v, -0.25 - 2.0 * u)
    np.testing.assert_allclose(t.matrix() @ [u, v, 1.0], [*expected, 1.0], atol=1e-12)


def data_uri(payload: bytes, mime: str = "application/octet-stream") -> str:
    return f"data:{mime};base64," + base64.b64encode(payload).decode()


def quad_gltf(buffer_uri: str, image_uri: str, buffer_bytes: int, extra: dict | None = None) -> dict:
    """A hand-written .gltf of the unit quad: positions (48 bytes), uvs (32), indices (12)."""
    document = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "translation": [1.0, 2.0, 3.0]}],
        "meshes": [
            {
                "name": "quad",
                "primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": 0}],
            }
        ],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0}}],
        "textures": [{"source": 0}],
        "images": [{"uri": image_uri}],
        "buffers": [{"uri": buffer_uri, "byteLength": buffer_bytes}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 48},
            {"buffer": 0, "byteOffset": 48, "byteLength": 32},
            {"buffer": 0, "byteOffset": 80, "byteLength": 12},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
            {"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"},
        ],
    }
    document.update(extra or {})
    return document


def quad_buffer() -> bytes:
    return (
        QUAD_POSITIONS.astype("<f4").tobytes()
        + QUAD_UVS.astype("<f4").tobytes()
        + QUAD_FACES.reshape(-1).astype("<u2").tobytes()
    )


IMAGE = quantised(np.random.default_rng(1).uniform(size=(2, 3, 3)))


def test_gltf_with_external_files_and_with_data_uris(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "quad.bin").write_bytes(quad_buffer())
    (tmp_path / "sub" / "colour map.png").write_bytes(png_bytes(IMAGE))
    external = tmp_path / "external.gltf"
    external.write_text(json.dumps(quad_gltf("sub/quad.bin", "sub/colour%20map.png", 92)))
    inline = tmp_path / "inline.gltf"
    inline.write_text(json.dumps(quad_gltf(data_uri(quad_buffer()), data_uri(png_bytes(IMAGE), "image/png"), 92)))
    for path in (external, inline):
        asset = read_gltf(path)
        np.testing.assert_allclose(asset.primitives[0].positions, QUAD_POSITIONS + [1, 2, 3])
        np.testing.assert_array_equal(asset.primitives[0].indices, QUAD_FACES)
        np.testing.assert_allclose(asset.materials[0].base_color_texture.image, IMAGE, atol=1e-6)
        assert asset.materials[0].metallic_factor == 0.0 and asset.materials[0].roughness_factor == 1.0


def bad(tmp_path, document: dict | None = None, name: str = "bad.gltf", raw: bytes | None = None) -> str:
    path = tmp_path / name
    path.write_bytes(raw if raw is not None else json.dumps(document).encode())
    with pytest.raises(DataError) as error:
        read_gltf(path)
    message = str(error.value)
    assert message.startswith(str(path)) and "\n" not in message
    return message


@pytest.mark.parametrize(
    "extension", ["KHR_texture_basisu", "KHR_draco_mesh_compression", "EXT_meshopt_compression", "EXT_unknown_thing"]
)
def test_required_extension_we_cannot_read_is_named(tmp_path, extension):
    document = quad_gltf(
        data_uri(quad_buffer()),
        data_uri(png_bytes(IMAGE), "image/png"),
        92,
        {"extensionsUsed": [extension], "extensionsRequired": [extension]},
    )
    message = bad(tmp_path, document)
    assert extension in message and "re-export" in message and "PNG/JPEG" in message


def test_bad_files_each_get_one_line_naming_the_file(tmp_path):
    path = tmp_path / "good.glb"
    write_glb(path, [Primitive("quad", QUAD_POSITIONS, QUAD_FACES)], [])
    data = path.read_bytes()
    assert "truncated" in bad(tmp_path, raw=data[: len(data) - 8], name="cut.glb")
    assert "truncated" in bad(tmp_path, raw=data[:10], name="tiny.glb")
    assert "quad.bin" in bad(tmp_path, quad_gltf("quad.bin", data_uri(png_bytes(IMAGE), "image/png"), 92))
    assert "missing.png" in bad(tmp_path, quad_gltf(data_uri(quad_buffer()), "missing.png", 92), name="noimage.gltf")
    assert "does not decode" in bad(
        tmp_path, quad_gltf(data_uri(quad_buffer()), data_uri(b"\x89PNG not really", "image/png"), 92), name="img.gltf"
    )
    assert "no triangles" in bad(tmp_path, {"asset": {"version": "2.0"}, "scenes": [{"nodes": []}]}, name="empty.gltf")
    points = quad_gltf(data_uri(quad_buffer()), data_uri(png_bytes(IMAGE), "image/png"), 92)
    points["meshes"][0]["primitives"][0]["mode"] = 0
    assert "no triangles" in bad(tmp_path, points, name="points.gltf")
    nan = QUAD_POSITIONS.astype("<f4")
    nan[2, 1] = np.nan
    payload = nan.tobytes() + quad_buffer()[48:]
    assert "not finite" in bad(
        tmp_path, quad_gltf(data_uri(payload), data_uri(png_bytes(IMAGE), "image/png"), 92), name="nan.gltf"
    )
    assert "JSON" in bad(tmp_path, raw=b"{not json", name="broken.gltf")
    assert "glTF 2.0" in bad(tmp_path, {"asset": {"version": "1.0"}}, name="old.gltf")
    assert "no such file" in str(pytest.raises(DataError, read_gltf, tmp_path / "absent.glb").value)


def test_node_hierarchy_with_trs_and_matrix_places_every_primitive(tmp_path):
    half = math.sqrt(0.5)
    document = quad_gltf(data_uri(quad_buffer()), data_uri(png_bytes(IMAGE), "image/png"), 92)
    document["scenes"] = [{"nodes": [0]}]
    document["nodes"] = [
        {
            "translation": [1.0, 2.0, 3.0],
            "rotation": [0.0, 0.0, half, half],
            "scale": [2.0, 2.0, 2.0],
            "children": [1, 2],
        },
        {"mesh": 0, "matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0.5, 0, 0, 1]},  # column-major: translate x by 0.5
        {"mesh": 1, "scale": [-1.0, 1.0, 1.0]},  # mirrored: the winding turns round
        {"mesh": 0},  # not in the scene
    ]
    document["meshes"].append(
        {
            "name": "dots",
            "primitives": [{"attributes": {"POSITION": 0}, "mode": 0}, {"attributes": {"POSITION": 0}, "indices": 2}],
        }
    )
    path = tmp_path / "tree.gltf"
    path.write_text(json.dumps(document))
    asset = read_gltf(path)
    assert [p.name for p in asset.primitives] == ["quad", "dots/1"]
    assert asset.notes == ["points primitives (skipped)"]
    rotate = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # +90 degrees about z
    expected = (2.0 * (QUAD_POSITIONS + [0.5, 0, 0])) @ rotate.T + [1, 2, 3]
    np.testing.assert_allclose(asset.primitives[0].positions, expected, atol=1e-12)
    np.testing.assert_array_equal(asset.primitives[0].indices, QUAD_FACES)
    mirrored = (2.0 * (QUAD_POSITIONS * [-1, 1, 1])) @ rotate.T + [1, 2, 3]
    np.testing.assert_allclose(asset.primitives[1].positions, mirrored, atol=1e-12)
    np.testing.assert_array_equal(asset.primitives[1].indices, QUAD_FACES[:, [0, 2, 1]])
    assert asset.primitives[1].material is None and asset.material_of(asset.primitives[1]) == PbrMaterial()


def test_what_is_ignored_is_listed_once(tmp_path):
    document = quad_gltf(
        data_uri(quad_buffer()),
        data_uri(png_bytes(IMAGE), "image/png"),
        92,
        {"extensionsUsed": ["KHR_materials_clearcoat"]},
    )
    document["materials"][0].update(
        {
            "normalTexture": {"index": 0},
            "occlusionTexture": {"index": 0},
            "emissiveFactor": [1, 0, 0],
            "alphaMode": "BLEND",
            "extensions": {"KHR_materials_clearcoat": {"clearcoatFactor": 1}},
        }
    )
    document["materials"].append(dict(document["materials"][0]))
    document["meshes"][0]["primitives"].append(dict(document["meshes"][0]["primitives"][0], material=1))
    path = tmp_path / "extras.gltf"
    path.write_text(json.dumps(document))
    asset = read_gltf(path)
    assert asset.notes == [
        "alpha mode BLEND",
        "emissive factors",
        "extension KHR_materials_clearcoat",
        "normal textures",
        "occlusion textures",
    ]
    assert len(asset.primitives) == 2 and asset.materials[0].base_color_texture is not None
