"""Textured triangle meshes as files: glTF 2.0 binary (``.glb``) and Wavefront OBJ + MTL + PNG.

A :class:`TexturedMesh` holds one texture (e.g. the panorama a room was seen in) and named groups of
triangles (``floor``, ``ceiling``, ``walls``). Both writers are written by hand from the formats' own
specifications:

* **glTF 2.0 binary** (Khronos glTF 2.0 specification, section "GLB File Format Specification"): a 12-byte
  header (magic ``glTF``, version 2, total length), a JSON chunk padded with spaces to 4 bytes and a BIN chunk
  padded with zeros to 4 bytes; one buffer (no ``uri``) holds, per group, ``POSITION`` (float32 VEC3 with its
  ``min``/``max``, as the specification requires), ``TEXCOORD_0`` (float32 VEC2) and the indices (uint32), then
  the PNG texture (an ``image`` with a ``bufferView`` and ``mimeType``). Every ``bufferView`` starts on a
  4-byte boundary. One node and one mesh per group, one material: the texture as ``baseColorTexture``,
  metallic 0, rough 1, double sided, and ``KHR_materials_unlit`` (a panorama is already lit; viewers without the
  extension fall back to the PBR material). The sampler repeats in ``u`` (a panorama wraps) and clamps in ``v``.
  glTF texture coordinates have ``(0, 0)`` at the top-left of the image, ``v`` down: :attr:`TexturedMesh.uv`.
* **OBJ** (``v``, ``vt``, ``f v/vt``; 1-based) with ``mtllib``/``usemtl`` and an MTL whose ``map_Kd`` is a PNG
  beside it. OBJ's ``vt`` has ``v`` up from the bottom of the image, so ``vt = (u, 1 - v)``. File names in
  ``mtllib``/``map_Kd`` cannot hold spaces, so the MTL and PNG names are the OBJ's stem with every character
  other than letters, digits, ``-``, ``_`` and ``.`` replaced by ``_``.

Coordinates are written as given (omnidl's meshes use the gravity-aligned y-up frame of the PLY point clouds,
:mod:`omnidl.viz.ply`, which is also glTF's +y up). Faces are counter-clockwise seen from their front; both
formats are written atomically, and an existing file is never replaced unless ``overwrite=True``.

:func:`read_glb` is a small reader of what :func:`write_glb` writes (header, chunks, accessors), for tests and
tools; it checks the structure and raises ``ValueError`` naming the file and what is wrong.
"""
from __future__ import annotations

import json
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from omnidl.utils.io import atomic_write_bytes, atomic_write_text

GLB_MAGIC = 0x46546C67          # b"glTF" little-endian
GLB_VERSION = 2
CHUNK_JSON = 0x4E4F534A         # b"JSON"
CHUNK_BIN = 0x004E4942          # b"BIN\0"
#: glTF enums (glTF 2.0 specification, "accessor.componentType", "bufferView.target", "sampler")
FLOAT, UNSIGNED_INT = 5126, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
LINEAR, LINEAR_MIPMAP_LINEAR, REPEAT, CLAMP_TO_EDGE = 9729, 9987, 10497, 33071
TRIANGLES = 4
_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}
_DTYPES = {FLOAT: "<f4", UNSIGNED_INT: "<u4"}


@dataclass
class TexturedMesh:
    """A triangle mesh with one RGB texture.

    Attributes:
        positions: ``(V, 3)`` float vertex positions (metres, in ``frame``).
        uv: ``(V, 2)`` texture coordinates in [0, 1], glTF convention: ``(0, 0)`` is the top-left corner of the
            texture image, ``u`` to the right, ``v`` down (pixel ``(x, y)`` of a ``W x H`` image is
            ``(x / W, y / H)``, pixel centres at +0.5).
        faces: ``(F, 3)`` vertex indices, counter-clockwise seen from the front of each face.
        texture: ``(H, W, 3)`` uint8 RGB image.
        groups: ``[(name, first_face, end_face), ...]`` consecutive face ranges (e.g. floor, ceiling, walls).
        frame: a sentence naming the coordinate frame (written into both files).
        info: diagnostics of whoever built the mesh (counts, tessellation step, ...).
    """

    positions: np.ndarray
    uv: np.ndarray
    faces: np.ndarray
    texture: np.ndarray
    groups: list[tuple[str, int, int]] = field(default_factory=list)
    frame: str = ""
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.positions = np.asarray(self.positions, np.float64)
        self.uv = np.asarray(self.uv, np.float64)
        self.faces = np.asarray(self.faces, np.int64).reshape(-1, 3)
        self.texture = np.asarray(self.texture)
        V = len(self.positions)
        if self.positions.ndim != 2 or self.positions.shape[1] != 3:
            raise ValueError(f"TexturedMesh: positions must be (V, 3), got {self.positions.shape}")
        if self.uv.shape != (V, 2):
            raise ValueError(f"TexturedMesh: uv must be (V, 2) = ({V}, 2), got {self.uv.shape}")
        if not (np.isfinite(self.positions).all() and np.isfinite(self.uv).all()):
            raise ValueError("TexturedMesh: positions and uv must be finite")
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= V):
            raise ValueError(f"TexturedMesh: face indices must lie in [0, {V}), got [{self.faces.min()}, "
                             f"{self.faces.max()}]")
        if self.texture.dtype != np.uint8 or self.texture.ndim != 3 or self.texture.shape[2] != 3:
            raise ValueError(f"TexturedMesh: texture must be (H, W, 3) uint8 RGB, got {self.texture.shape} "
                             f"{self.texture.dtype}")
        if not self.groups:
            self.groups = [("mesh", 0, len(self.faces))]
        end = 0
        for name, a, b in self.groups:
            if a != end or b < a:
                raise ValueError(f"TexturedMesh: groups must be consecutive face ranges from 0, got {self.groups}")
            end = b
        if end != len(self.faces):
            raise ValueError(f"TexturedMesh: groups cover {end} faces of {len(self.faces)}")

    def group(self, name: str) -> np.ndarray:
        """``(F_g, 3)`` faces of the group ``name``."""
        for n, a, b in self.groups:
            if n == name:
                return self.faces[a:b]
        raise KeyError(f"no group {name!r} (groups: {[g[0] for g in self.groups]})")


def _free(paths: list[Path], overwrite: bool) -> None:
    """Refuse (``FileExistsError`` naming the file) when any of ``paths`` exists and ``overwrite`` is False."""
    if overwrite:
        return
    for p in paths:
        if p.exists() or p.is_symlink():
            raise FileExistsError(f"{p} already exists; not replacing it (pass overwrite=True, or --overwrite on "
                                  "the command line, to replace it)")


def _png(texture: np.ndarray) -> bytes:
    import cv2
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(texture[:, :, ::-1]))
    if not ok:
        raise ValueError(f"could not encode the {texture.shape[1]}x{texture.shape[0]} texture as PNG")
    return buf.tobytes()


def _pad(data: bytes, fill: bytes) -> bytes:
    return data + fill * (-len(data) % 4)


def glb_bytes(mesh: TexturedMesh, name: str = "omnidl mesh") -> bytes:
    """The ``.glb`` file of ``mesh`` (module docstring) as bytes."""
    blob = bytearray()
    views: list[dict] = []
    accessors: list[dict] = []

    def view(data: bytes, target: int | None) -> int:
        blob.extend(b"\0" * (-len(blob) % 4))
        v = {"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)}
        if target is not None:
            v["target"] = target
        blob.extend(data)
        views.append(v)
        return len(views) - 1

    def accessor(arr: np.ndarray, ctype: int, kind: str, target: int, bounds: bool = False) -> int:
        a = np.ascontiguousarray(arr, _DTYPES[ctype])
        acc = {"bufferView": view(a.tobytes(), target), "componentType": ctype, "count": int(len(a)), "type": kind}
        if bounds:
            acc["min"] = [float(x) for x in a.min(0)]
            acc["max"] = [float(x) for x in a.max(0)]
        accessors.append(acc)
        return len(accessors) - 1

    meshes, nodes = [], []
    for gname, a, b in mesh.groups:
        faces = mesh.faces[a:b]
        if not len(faces):
            continue
        used, local = np.unique(faces, return_inverse=True)
        pos = mesh.positions[used].astype(np.float32)
        prim = {"attributes": {"POSITION": accessor(pos, FLOAT, "VEC3", ARRAY_BUFFER, bounds=True),
                               "TEXCOORD_0": accessor(mesh.uv[used], FLOAT, "VEC2", ARRAY_BUFFER)},
                "indices": accessor(local.reshape(-1), UNSIGNED_INT, "SCALAR", ELEMENT_ARRAY_BUFFER),
                "material": 0, "mode": TRIANGLES}
        meshes.append({"name": gname, "primitives": [prim]})
        nodes.append({"name": gname, "mesh": len(meshes) - 1})
    image_view = view(_png(mesh.texture), None)
    doc = {
        "asset": {"version": "2.0", "generator": "omnidl", **({"extras": {"frame": mesh.frame}} if mesh.frame else {})},
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0,
        "scenes": [{"name": name, "nodes": list(range(len(nodes)))}],
        "nodes": nodes,
        "meshes": meshes,
        "materials": [{"name": "texture", "doubleSided": True,
                       "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0,
                                                "roughnessFactor": 1.0},
                       "extensions": {"KHR_materials_unlit": {}}}],
        "textures": [{"sampler": 0, "source": 0}],
        "samplers": [{"magFilter": LINEAR, "minFilter": LINEAR_MIPMAP_LINEAR, "wrapS": REPEAT,
                      "wrapT": CLAMP_TO_EDGE}],
        "images": [{"bufferView": image_view, "mimeType": "image/png"}],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": len(blob)}],
    }
    js = _pad(json.dumps(doc, separators=(",", ":"), ensure_ascii=True).encode("utf-8"), b" ")
    bin_ = _pad(bytes(blob), b"\0")
    total = 12 + 8 + len(js) + 8 + len(bin_)
    return (struct.pack("<III", GLB_MAGIC, GLB_VERSION, total) + struct.pack("<II", len(js), CHUNK_JSON) + js
            + struct.pack("<II", len(bin_), CHUNK_BIN) + bin_)


def write_glb(path: str | Path, mesh: TexturedMesh, overwrite: bool = False) -> Path:
    """Write ``mesh`` as glTF binary to ``path`` (atomically; an existing file only with ``overwrite``)."""
    path = Path(path)
    _free([path], overwrite)
    return atomic_write_bytes(path, glb_bytes(mesh, name=path.stem))


def read_glb(source: str | Path | bytes) -> tuple[dict, bytes]:
    """Parse a ``.glb``: ``(json document, BIN chunk)``, after checking the header, the chunk layout, and that
    every buffer view lies inside the BIN chunk and every accessor inside its view. ``ValueError`` otherwise."""
    where = "glb data" if isinstance(source, (bytes, bytearray)) else str(source)
    data = bytes(source) if isinstance(source, (bytes, bytearray)) else Path(source).read_bytes()

    def bad(msg: str) -> ValueError:
        return ValueError(f"{where}: not a valid glTF binary: {msg}")

    if len(data) < 20:
        raise bad(f"{len(data)} bytes, shorter than a header and a chunk header")
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != GLB_MAGIC:
        raise bad(f"magic {magic:#x}, expected {GLB_MAGIC:#x} ('glTF')")
    if version != GLB_VERSION:
        raise bad(f"version {version}, expected 2")
    if length != len(data) or length % 4:
        raise bad(f"header length {length} but the file has {len(data)} bytes (must match, multiple of 4)")
    chunks, off = [], 12
    while off < length:
        if off + 8 > length:
            raise bad(f"truncated chunk header at byte {off}")
        clen, ctype = struct.unpack_from("<II", data, off)
        if clen % 4 or off + 8 + clen > length:
            raise bad(f"chunk at byte {off} has length {clen} (must be a multiple of 4 inside the file)")
        chunks.append((ctype, data[off + 8:off + 8 + clen]))
        off += 8 + clen
    if not chunks or chunks[0][0] != CHUNK_JSON:
        raise bad("the first chunk must be JSON")
    try:
        doc = json.loads(chunks[0][1].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise bad(f"JSON chunk: {e}") from e
    binary = chunks[1][1] if len(chunks) > 1 and chunks[1][0] == CHUNK_BIN else b""
    if doc.get("asset", {}).get("version") != "2.0":
        raise bad(f"asset.version {doc.get('asset', {}).get('version')!r}, expected '2.0'")
    buffers = doc.get("buffers", [])
    if buffers and not (buffers[0].get("byteLength", -1) <= len(binary) < buffers[0]["byteLength"] + 4):
        raise bad(f"buffers[0].byteLength {buffers[0].get('byteLength')} does not match the BIN chunk "
                  f"({len(binary)} bytes, padded by at most 3)")
    for i, v in enumerate(doc.get("bufferViews", [])):
        if v.get("byteOffset", 0) + v["byteLength"] > (buffers[v["buffer"]]["byteLength"] if buffers else 0):
            raise bad(f"bufferViews[{i}] runs past its buffer")
    for i, a in enumerate(doc.get("accessors", [])):
        v = doc["bufferViews"][a["bufferView"]]
        size = np.dtype(_DTYPES[a["componentType"]]).itemsize * _COMPONENTS[a["type"]] * a["count"]
        if a.get("byteOffset", 0) + size > v["byteLength"]:
            raise bad(f"accessors[{i}] ({a['count']} x {a['type']}) runs past bufferViews[{a['bufferView']}]")
        if (v.get("byteOffset", 0) + a.get("byteOffset", 0)) % np.dtype(_DTYPES[a["componentType"]]).itemsize:
            raise bad(f"accessors[{i}] is not aligned to its component size")
    return doc, binary


def glb_accessor(doc: dict, binary: bytes, index: int) -> np.ndarray:
    """The values of accessor ``index`` of a parsed ``.glb`` (:func:`read_glb`) as an array ``(count, n)``."""
    a = doc["accessors"][index]
    v = doc["bufferViews"][a["bufferView"]]
    n = _COMPONENTS[a["type"]]
    start = v.get("byteOffset", 0) + a.get("byteOffset", 0)
    arr = np.frombuffer(binary, _DTYPES[a["componentType"]], count=a["count"] * n, offset=start)
    return arr.reshape(a["count"], n)


def _file_token(stem: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]", "_", stem) or "_"


def obj_text(mesh: TexturedMesh, mtl_name: str, material: str = "texture") -> str:
    """The OBJ text of ``mesh`` (``vt`` flipped to OBJ's bottom-left origin), one ``o`` per group."""
    lines = ["# omnidl textured mesh" + (f"; {mesh.frame}" if mesh.frame else ""),
             f"mtllib {mtl_name}"]
    lines += [f"v {p[0]:.6f} {p[1]:.6f} {p[2]:.6f}" for p in mesh.positions]
    lines += [f"vt {t[0]:.7f} {1.0 - t[1]:.7f}" for t in mesh.uv]
    for gname, a, b in mesh.groups:
        lines += [f"o {_file_token(gname)}", f"usemtl {material}"]
        lines += [f"f {i + 1}/{i + 1} {j + 1}/{j + 1} {k + 1}/{k + 1}" for i, j, k in mesh.faces[a:b]]
    return "\n".join(lines) + "\n"


def obj_paths(path: str | Path) -> tuple[Path, Path, Path]:
    """``(obj, mtl, png)`` paths :func:`write_obj` writes for ``path``."""
    path = Path(path)
    token = _file_token(path.stem)
    return path, path.with_name(f"{token}.mtl"), path.with_name(f"{token}_texture.png")


def write_obj(path: str | Path, mesh: TexturedMesh, overwrite: bool = False) -> list[Path]:
    """Write ``mesh`` as ``path`` (OBJ), an MTL and the texture PNG beside it (:func:`obj_paths`); nothing is
    written when any of the three exists, unless ``overwrite``. Returns the three paths."""
    obj, mtl, png = obj_paths(path)
    if obj.suffix.lower() != ".obj":
        raise ValueError(f"write_obj: {obj} should end in .obj")
    _free([obj, mtl, png], overwrite)
    mtl_text = ("# omnidl textured mesh material\nnewmtl texture\nKa 1.000 1.000 1.000\nKd 1.000 1.000 1.000\n"
                f"Ks 0.000 0.000 0.000\nd 1.0\nillum 1\nmap_Kd {png.name}\n")
    atomic_write_bytes(png, _png(mesh.texture))
    atomic_write_text(mtl, mtl_text)
    atomic_write_text(obj, obj_text(mesh, mtl.name))
    return [obj, mtl, png]
