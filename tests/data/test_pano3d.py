import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from omnidl.data.exr import read_exr, read_exr_builtin, read_exr_depth
from omnidl.data.pano3d import Pano3D, read_pair_list


def write_exr(path: Path, planes: dict, compression: int = 0) -> None:
    """A single-part scanline EXR written from the OpenEXR file-layout spec (NONE = 0 or ZIPS = 2)."""
    names = sorted(planes)
    h, w = planes[names[0]].shape
    types = {np.dtype("float16"): 1, np.dtype("float32"): 2, np.dtype("uint32"): 0}

    def attr(name, typ, data):
        return name.encode() + b"\0" + typ.encode() + b"\0" + struct.pack("<i", len(data)) + data
    ch = b"".join(n.encode() + b"\0" + struct.pack("<iB3sii", types[planes[n].dtype], 0, b"\0\0\0", 1, 1)
                  for n in names) + b"\0"
    box = struct.pack("<iiii", 0, 0, w - 1, h - 1)
    head = struct.pack("<iI", 20000630, 2) + attr("channels", "chlist", ch) + \
        attr("compression", "compression", bytes([compression])) + attr("dataWindow", "box2i", box) + \
        attr("displayWindow", "box2i", box) + attr("lineOrder", "lineOrder", b"\0") + \
        attr("pixelAspectRatio", "float", struct.pack("<f", 1)) + \
        attr("screenWindowCenter", "v2f", struct.pack("<ff", 0, 0)) + \
        attr("screenWindowWidth", "float", struct.pack("<f", 1)) + b"\0"
    chunks = []
    for y in range(h):
        raw = b"".join(planes[n][y].astype(planes[n].dtype.newbyteorder("<")).tobytes() for n in names)
        if compression == 2:
            b = np.frombuffer(raw, np.uint8)
            inter = np.concatenate([b[0::2], b[1::2]]).astype(np.int64)
            pred = np.concatenate([inter[:1], (np.diff(inter) + 128) % 256]).astype(np.uint8)
            comp = zlib.compress(pred.tobytes())
            raw = comp if len(comp) < len(raw) else raw
        chunks.append(struct.pack("<ii", y, len(raw)) + raw)
    pos = len(head) + 8 * h
    offsets = []
    for c in chunks:
        offsets.append(pos)
        pos += len(c)
    path.write_bytes(head + struct.pack(f"<{h}Q", *offsets) + b"".join(chunks))


@pytest.mark.parametrize("compression", [0, 2])
def test_reader_on_spec_written_files(tmp_path, compression):
    rng = np.random.default_rng(0)
    d = (rng.random((6, 10)) * 8).astype(np.float32)
    d[2, 3:9] = 1.25                                     # a run, so ZIPS actually compresses
    write_exr(tmp_path / "d.exr", {"Y": d, "A": d.astype(np.float16)}, compression)
    for reader in (read_exr, read_exr_builtin):                  # the OpenEXR package and the fallback agree
        planes = reader(tmp_path / "d.exr")
        assert np.array_equal(planes["Y"], d) and np.array_equal(planes["A"], d.astype(np.float16))
    assert np.array_equal(read_exr_depth(tmp_path / "d.exr"), d)


@pytest.mark.parametrize("comp", ["NO_COMPRESSION", "RLE_COMPRESSION", "ZIPS_COMPRESSION", "ZIP_COMPRESSION"])
def test_reader_matches_openexr(tmp_path, comp):
    OpenEXR = pytest.importorskip("OpenEXR")
    rng = np.random.default_rng(1)
    d = (rng.random((37, 50)) * 10).astype(np.float32)
    d[5:20, 5:40] = 3.5
    OpenEXR.File({"compression": getattr(OpenEXR, comp), "type": OpenEXR.scanlineimage},
                 {"Y": d, "H": d.astype(np.float16), "U": (d * 100).astype(np.uint32)}).write(str(tmp_path / "o.exr"))
    for reader in (read_exr, read_exr_builtin):
        p = reader(tmp_path / "o.exr")
        assert np.array_equal(p["Y"], d) and np.array_equal(p["H"], d.astype(np.float16))
        assert np.array_equal(p["U"], (d * 100).astype(np.uint32))


def write_views(root: Path, n=2, w=32, h=16):
    truth = {}
    (root / "M3D").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(2)
    lines = []
    for i in range(n):
        rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        d = (rng.random((h, w)) * 12).astype(np.float32)
        d[0, :4] = np.inf
        stem = f"v{i}"
        cv2.imwrite(str(root / "M3D" / f"{stem}_color_0_Left_Down_0.0.png"), rgb[..., ::-1])
        write_exr(root / "M3D" / f"{stem}_depth_0_Left_Down_0.0.exr", {"Y": d}, 2)
        lines.append(f"M3D/{stem}_color_0_Left_Down_0.0.png M3D/{stem}_depth_0_Left_Down_0.0.exr")
        truth[stem] = (rgb, d)
    (root / "test.txt").write_text("\n".join(lines) + "\n")
    return truth


def test_pano3d_samples(tmp_path):
    truth = write_views(tmp_path)
    ds = Pano3D(tmp_path, split_file=tmp_path / "test.txt", height=None, width=None)
    assert len(ds) == 2 and len(Pano3D(tmp_path, height=None, width=None)) == 2
    s = ds[1]
    rgb, d = truth["v1"]
    want = np.where(np.isfinite(d) & (d <= 10), d, 0)
    assert np.array_equal(s["depth"][0].numpy(), want)
    assert s["meta"]["invalid_depth"] == int((~(np.isfinite(d) & (d <= 10))).sum())
    assert np.allclose(s["image"].permute(1, 2, 0).numpy() * 255, rgb, atol=0.5)
    small = Pano3D(tmp_path, height=8, width=16)[0]
    assert small["image"].shape == (3, 8, 16) and small["depth"].shape == (1, 8, 16)
    assert read_pair_list(tmp_path / "test.txt")[0][0].startswith("M3D/v0")


def test_config(tmp_path):
    import sys
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from adapter_fixtures import instantiate_split
    write_views(tmp_path / "d")
    ds = instantiate_split(tmp_path, "pano3d", tmp_path / "d", "test",
                           [f"data.test_list={tmp_path / 'd' / 'test.txt'}", "data.height=8", "data.width=16"])
    assert len(ds) == 2 and ds[0]["depth"].shape == (1, 8, 16)
