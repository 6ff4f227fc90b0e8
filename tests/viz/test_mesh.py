"""Textured meshes as glTF binary and OBJ + MTL: the files follow the formats' specifications (checked by parsing
them back by hand and, when installed, with pygltflib and trimesh) and never replace an existing file."""
from __future__ import annotations

import json
import struct

import cv2
import numpy as np
import pytest

from omnidl.viz.mesh import (CHUNK_BIN, CHUNK_JSON, GLB_MAGIC, TexturedMesh, glb_accessor, glb_bytes, obj_paths,
                             read_glb, write_glb, write_obj)


def _mesh(groups=True) -> TexturedMesh:
    """A unit square (two triangles, one per group) with a 4x2 texture."""
    pos = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], float)
    tex = np.arange(24, dtype=np.uint8).reshape(2, 4, 3) * 10
    return TexturedMesh(pos, uv, [[0, 1, 2], [0, 2, 3]], tex,
                        [("floor", 0, 1), ("walls", 1, 2)] if groups else [], frame="test frame")


def test_glb_layout_follows_the_specification():
    data = glb_bytes(_mesh())
    magic, version, length = struct.unpack_from("<III", data)
    assert (magic, version, length) == (GLB_MAGIC, 2, len(data)) and data[:4] == b"glTF" and length % 4 == 0
    jlen, jtype = struct.unpack_from("<II", data, 12)
    assert jtype == CHUNK_JSON and jlen % 4 == 0
    doc = json.loads(data[20:20 + jlen])                                 # padded with spaces: still valid JSON
    blen, btype = struct.unpack_from("<II", data, 20 + jlen)
    assert btype == CHUNK_BIN and blen % 4 == 0 and 28 + jlen + blen == len(data)
    assert doc["asset"]["version"] == "2.0" and doc["buffers"][0]["byteLength"] <= blen < doc["buffers"][0][
        "byteLength"] + 4 and "uri" not in doc["buffers"][0]
    assert all(v["byteOffset"] % 4 == 0 for v in doc["bufferViews"])
    assert [m["name"] for m in doc["meshes"]] == ["floor", "walls"] and doc["scenes"][0]["nodes"] == [0, 1]
    pos = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    assert pos["min"] == [0.0, 0.0, 0.0] and pos["max"] == [1.0, 1.0, 0.0]   # required for POSITION
    img = doc["images"][0]
    assert img["mimeType"] == "image/png" and "target" not in doc["bufferViews"][img["bufferView"]]
    assert doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] == {"index": 0}


def test_glb_round_trip_through_the_reader():
    mesh = _mesh()
    doc, binary = read_glb(glb_bytes(mesh))
    prim = doc["meshes"][1]["primitives"][0]
    p = glb_accessor(doc, binary, prim["attributes"]["POSITION"])
    t = glb_accessor(doc, binary, prim["attributes"]["TEXCOORD_0"])
    i = glb_accessor(doc, binary, prim["indices"]).reshape(-1, 3)
    np.testing.assert_allclose(p[i], mesh.positions[mesh.faces[1:]])
    np.testing.assert_allclose(t[i], mesh.uv[mesh.faces[1:]])
    v = doc["bufferViews"][doc["images"][0]["bufferView"]]
    png = np.frombuffer(binary[v["byteOffset"]:v["byteOffset"] + v["byteLength"]], np.uint8)
    np.testing.assert_array_equal(cv2.imdecode(png, cv2.IMREAD_COLOR)[:, :, ::-1], mesh.texture)


@pytest.mark.parametrize("corrupt, match", [
    (lambda d: b"gltf" + d[4:], "magic"),
    (lambda d: d[:8] + struct.pack("<I", len(d) + 4) + d[12:], "header length"),
    (lambda d: d[:-4], "header length"),
    (lambda d: d[:12] + struct.pack("<II", 6, CHUNK_BIN) + d[20:], "chunk at byte 12|first chunk"),
    (lambda d: d[:10], "shorter than a header"),
])
def test_reader_names_what_is_wrong(corrupt, match):
    with pytest.raises(ValueError, match=match):
        read_glb(corrupt(glb_bytes(_mesh())))


def test_glb_never_replaces_a_file(tmp_path):
    p = tmp_path / "room.glb"
    p.write_bytes(b"mine")
    with pytest.raises(FileExistsError, match=r"room\.glb already exists.*overwrite"):
        write_glb(p, _mesh())
    assert p.read_bytes() == b"mine"
    write_glb(p, _mesh(), overwrite=True)
    assert read_glb(p)[0]["asset"]["generator"] == "omnidl"


def test_obj_mtl_png(tmp_path):
    mesh = _mesh()
    obj, mtl, png = write_obj(tmp_path / "my room.obj", mesh)
    assert (mtl.name, png.name) == ("my_room.mtl", "my_room_texture.png")   # no spaces in mtllib / map_Kd
    text = obj.read_text().splitlines()
    assert "mtllib my_room.mtl" in text and "o floor" in text and "usemtl texture" in text
    vts = np.array([[float(x) for x in ln.split()[1:]] for ln in text if ln.startswith("vt ")])
    np.testing.assert_allclose(vts, np.c_[mesh.uv[:, 0], 1 - mesh.uv[:, 1]])  # OBJ's v is up from the bottom
    faces = [ln for ln in text if ln.startswith("f ")]
    assert faces == ["f 1/1 2/2 3/3", "f 1/1 3/3 4/4"]
    assert f"map_Kd {png.name}" in mtl.read_text()
    np.testing.assert_array_equal(cv2.imread(str(png))[:, :, ::-1], mesh.texture)


def test_obj_refuses_before_writing_anything(tmp_path):
    obj, mtl, png = obj_paths(tmp_path / "room.obj")
    mtl.write_text("a user's material")
    with pytest.raises(FileExistsError, match=r"room\.mtl already exists"):
        write_obj(obj, _mesh())
    assert not obj.exists() and not png.exists() and mtl.read_text() == "a user's material"


@pytest.mark.parametrize("kwargs, match", [
    ({"positions": np.zeros((4, 2))}, "positions must be"),
    ({"uv": np.zeros((3, 2))}, "uv must be"),
    ({"faces": [[0, 1, 7]]}, "face indices"),
    ({"texture": np.zeros((2, 4, 3), np.float32)}, "uint8 RGB"),
    ({"uv": np.full((4, 2), np.nan)}, "finite"),
])
def test_mesh_checks_its_arrays(kwargs, match):
    m = _mesh(groups=False)
    args = {"positions": m.positions, "uv": m.uv, "faces": m.faces, "texture": m.texture, **kwargs}
    with pytest.raises(ValueError, match=match):
        TexturedMesh(**args)


def test_pygltflib_reads_it(tmp_path):
    pygltflib = pytest.importorskip("pygltflib")
    path = write_glb(tmp_path / "m.glb", _mesh())
    g = pygltflib.GLTF2().load(str(path))
    assert g.asset.version == "2.0" and len(g.meshes) == 2 and g.images[0].mimeType == "image/png"
    assert len(g.binary_blob()) >= g.buffers[0].byteLength


def test_trimesh_reads_glb_and_obj(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    mesh = _mesh()
    scene = trimesh.load(write_glb(tmp_path / "m.glb", mesh))
    assert sorted(scene.geometry) == ["floor", "walls"]
    obj = trimesh.load(write_obj(tmp_path / "m.obj", mesh)[0])
    assert len(obj.faces) == 2
    assert np.asarray(obj.visual.material.image).shape[:2] == mesh.texture.shape[:2]
