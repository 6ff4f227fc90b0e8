"""Invariants of the data layer for generated inputs (issue 48 items 3-6, issue 49 item 5), beside the tables.

Every generated bad input must get a named error, a flagged skip or the correct value -- never a silent wrong
target. The generators (Hypothesis, fixed seed, bounded examples):

* images: any EXIF orientation x format x channel layout -> the upright pixels PIL's ``exif_transpose`` shows;
  any truncation of any format -> a named error or the exact picture;
* ``label_cor`` of generated convex rooms, shuffled / duplicated / swapped / split-column / unit-scaled,
  through the HorizonNet folder and Structured3D -> a named error, or the room itself;
* PanoAnnotator / ZInD files in other units (cm, mm, x1e4) -> a named error or skip;
* depth in the wrong unit, NaN/inf in EXR -> a named error or counted invalid pixels;
* paths in dataset files with ``..`` / absolute -> an error naming the file and line.
"""
from __future__ import annotations

import io
import json
import math
import os
import shutil
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, assume, given, settings, strategies as st
from PIL import Image, ImageOps

from omnidl.data.robust import CorruptSampleError, SkipCorrupt
from omnidl.data.validate import DataValidationError, UnreadableFileError, read_raw
from tests.data.adapter_fixtures import (ROOMS, pano_annotator_label, write_pano_annotator, write_structured3d,
                                         write_zind)

PROPS = settings(max_examples=40, deadline=None, derandomize=True,
                 suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
FEW = settings(max_examples=15, deadline=None, derandomize=True,
               suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def _bgr_to_rgb(a: np.ndarray) -> np.ndarray:
    return a if a.ndim == 2 else np.ascontiguousarray(a[..., 2::-1] if a.shape[2] >= 3 else a)


def _pil_bytes(arr: np.ndarray, fmt: str, orientation: int) -> bytes:
    im = Image.fromarray(arr)
    ex = Image.Exif()
    ex[0x0112] = orientation
    b = io.BytesIO()
    kw = {"quality": 95} if fmt == "JPEG" else {"lossless": True} if fmt == "WEBP" else {}
    im.save(b, fmt, exif=ex, **kw)
    return b.getvalue()


# ============================================================================================ reading policy
@PROPS
@given(orientation=st.integers(1, 8), fmt=st.sampled_from(["PNG", "WEBP", "TIFF", "JPEG"]),
       gray=st.booleans(), h=st.integers(2, 9), w=st.integers(2, 9), seed=st.integers(0, 2 ** 16),
       flags=st.sampled_from([cv2.IMREAD_UNCHANGED, cv2.IMREAD_COLOR]))
def test_exif_orientation_is_pils_upright_view(tmp_path, orientation, fmt, gray, h, w, seed, flags):
    """Every reader path (any imdecode flags) shows the pixels PIL's exif_transpose shows, for every format."""
    rng = np.random.default_rng(seed)
    arr = rng.integers(0, 256, (h * 8, w * 8) if gray else (h * 8, w * 8, 3), dtype=np.uint8)
    arr = cv2.resize(arr, (w * 8, h * 8), interpolation=cv2.INTER_NEAREST)
    data = _pil_bytes(arr, fmt, orientation)
    f = tmp_path / f"x.{fmt.lower()}"
    f.write_bytes(data)
    want = np.asarray(ImageOps.exif_transpose(Image.open(io.BytesIO(data))))
    got = _bgr_to_rgb(read_raw(f, flags))
    if flags == cv2.IMREAD_COLOR and want.ndim == 2:
        want = np.repeat(want[..., None], 3, 2)
    if got.ndim == 3 and got.shape[2] == 1:
        got = got[..., 0]
    assert got.shape == want.shape
    if fmt == "JPEG":
        assert np.abs(got.astype(int) - want.astype(int)).mean() < 4
    else:
        assert np.array_equal(got, want)


def _upside_down_png(path: Path, upright_rgb: np.ndarray) -> None:
    """Write the pixels rotated by 180 degrees with EXIF orientation 3: a viewer shows ``upright_rgb``."""
    path.write_bytes(_pil_bytes(np.ascontiguousarray(upright_rgb[::-1, ::-1]), "PNG", 3))


def test_every_reader_gives_the_upright_image(tmp_path):
    """Regression (issue 48): ZInD / PanoAnnotator read the stored (upside-down) pixels while other readers turned
    the image upright. Now every reader, and so every adapter, gives the same upright pixels."""
    from omnidl.data.folder import ImageFolder
    from omnidl.data.horizon import read_rgb as horizon_rgb
    from omnidl.data.layout_sample import read_panorama
    from omnidl.data.readers import read_rgb
    rng = np.random.default_rng(0)
    upright = rng.integers(0, 256, (16, 32, 3), dtype=np.uint8)
    upright[:4] = 255                                               # a bright ceiling: upside down is obvious
    _upside_down_png(tmp_path / "p.png", upright)
    want = torch.from_numpy(upright).permute(2, 0, 1).float() / 255
    for got in (read_rgb(tmp_path / "p.png"), horizon_rgb(tmp_path / "p.png"),
                read_panorama(tmp_path / "p.png", None, None),
                ImageFolder(str(tmp_path), height=None, width=None)[0]["image"]):
        assert torch.allclose(got, want)


def test_pano_annotator_trains_on_the_upright_image(tmp_path):
    """Regression (issue 48): the layout of an EXIF-rotated panorama is the upright image's layout."""
    from omnidl.data.pano_annotator import PanoAnnotatorLayout
    write_pano_annotator(tmp_path, 64, 32)
    img = tmp_path / "image" / "scene0_box.png"
    upright = cv2.imread(str(img))[..., ::-1].copy()
    _upside_down_png(img, upright)
    s = PanoAnnotatorLayout(tmp_path, split="train", height=32, width=64)[0]
    assert torch.allclose(s["image"], torch.from_numpy(upright).permute(2, 0, 1).float() / 255)


@FEW
@given(kind=st.sampled_from(["zind", "pano_annotator"]))
def test_layout_adapters_apply_exif(tmp_path_factory, kind):
    from omnidl.data.pano_annotator import PanoAnnotatorLayout
    from omnidl.data.zind import ZInD
    root = tmp_path_factory.mktemp(kind)
    if kind == "zind":
        write_zind(root, 64, 32)
        img = sorted((root / "0000" / "panos").iterdir())[0]
        ds = lambda: ZInD(root, split="train", height=32, width=64)          # noqa: E731
    else:
        write_pano_annotator(root, 64, 32)
        img = root / "image" / "scene0_box.png"
        ds = lambda: PanoAnnotatorLayout(root, split="train", height=32, width=64)   # noqa: E731
    before = ds()[0]["image"]
    upright = (before.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    img.write_bytes(_pil_bytes(np.ascontiguousarray(upright[::-1, ::-1]), "JPEG" if img.suffix == ".jpg" else "PNG", 3))
    after = ds()[0]["image"]
    assert (after - before).abs().mean() < 0.03                    # JPEG re-encoding noise only, not a flip


def _weird(tmp_path: Path, name: bytes) -> Path:
    d = os.fsencode(str(tmp_path)) + b"/" + name
    return Path(os.fsdecode(d))


def test_file_names_of_any_bytes(tmp_path):
    """Regression (issue 48): a non-UTF-8 name reaches no native string binding (OpenCV segfaults on one)."""
    import OpenEXR
    from omnidl.data.exr import read_exr
    from omnidl.data.readers import iter_video_frames, read_label_map, read_rgb
    img = _weird(tmp_path, b"pano\xff\xfe.png")
    cv2.imwrite(str(tmp_path / "a.png"), np.full((8, 16, 3), 7, np.uint8))
    shutil.move(tmp_path / "a.png", img)
    assert read_rgb(img).shape == (3, 8, 16)
    lab = _weird(tmp_path, b"lab\xe9.png")
    Image.fromarray(np.arange(16, dtype=np.uint8).reshape(4, 4)).convert("P").save(tmp_path / "b.png")
    shutil.move(tmp_path / "b.png", lab)
    assert read_label_map(lab).shape == (4, 4)
    exr = _weird(tmp_path, b"d\xff.exr")
    OpenEXR.File({"compression": OpenEXR.PIZ_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"Y": np.ones((4, 6), np.float32)}).write(str(tmp_path / "d.exr"))
    shutil.move(tmp_path / "d.exr", exr)
    assert read_exr(exr)["Y"].shape == (4, 6)
    vid = _weird(tmp_path, b"v\xff.avi")
    wr = cv2.VideoWriter(str(tmp_path / "v.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 5, (16, 8))
    if not wr.isOpened():
        pytest.skip("OpenCV has no MJPG writer")
    for i in range(3):
        wr.write(np.full((8, 16, 3), 40 * i, np.uint8))
    wr.release()
    shutil.move(tmp_path / "v.avi", vid)
    frames = list(iter_video_frames(vid))
    assert len(frames) == 3 and frames[0].shape == (3, 8, 16)


def _png_header_only(w: int, h: int) -> bytes:
    import struct
    import zlib

    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 16)) + chunk(b"IEND", b""))


def test_pixel_limit_is_a_named_skip(tmp_path, caplog):
    """Regression (issue 48): an image over OpenCV's pixel limit raised a raw cv2.error without the file name
    and stopped training; it is now a CorruptSampleError naming the file, skipped with a warning."""
    from omnidl.data.folder import ImageFolder
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((8, 16, 3), np.uint8))
    (tmp_path / "huge.png").write_bytes(_png_header_only(50000, 50000))
    ds = ImageFolder(str(tmp_path), height=None, width=None)
    with pytest.raises(UnreadableFileError, match=r"huge\.png.*CV_IO_MAX_IMAGE_PIXELS"):
        ds[1]
    robust = SkipCorrupt(ds)
    assert robust[0] is not None
    with caplog.at_level("WARNING", logger="omnidl.data"):
        assert robust[1] is None
    assert "huge.png" in caplog.text


@PROPS
@given(fmt=st.sampled_from([".png", ".jpg", ".webp", ".tiff"]), keep=st.floats(0.05, 0.999), seed=st.integers(0, 99))
def test_truncated_file_is_a_named_error_or_the_exact_picture(tmp_path, fmt, keep, seed):
    rng = np.random.default_rng(seed)
    arr = cv2.resize(rng.integers(0, 256, (4, 8, 3), dtype=np.uint8), (64, 32), interpolation=cv2.INTER_NEAREST)
    data = cv2.imencode(fmt, arr)[1].tobytes()
    full = tmp_path / f"full{fmt}"
    full.write_bytes(data)
    cut = tmp_path / f"cut{fmt}"
    cut.write_bytes(data[: max(1, int(len(data) * keep))])
    try:
        got = read_raw(cut)
    except UnreadableFileError as e:
        assert "cut" + fmt in str(e)
        return
    assert np.array_equal(got, read_raw(full))


@pytest.mark.parametrize("kind", ["gray8", "gray16", "rgb16", "rgba", "gray_alpha", "palette"])
def test_colour_policy(tmp_path, kind):
    """16-bit, alpha, palette and grayscale images read as docs/data.md says."""
    from omnidl.data.readers import read_label_map, read_rgb
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (4, 6, 3), dtype=np.uint8)
    g = rgb[..., 0]
    f = tmp_path / "x.png"
    if kind == "gray8":
        cv2.imwrite(str(f), g)
        want = np.repeat(g[..., None], 3, 2) / 255
    elif kind == "gray16":
        cv2.imwrite(str(f), g.astype(np.uint16) * 256 + 1)
        want = np.repeat((g.astype(np.float64) * 256 + 1)[..., None], 3, 2) / 65535
    elif kind == "rgb16":
        cv2.imwrite(str(f), (rgb.astype(np.uint16) * 256)[..., ::-1])
        want = rgb.astype(np.float64) * 256 / 65535
    elif kind == "rgba":
        cv2.imwrite(str(f), np.concatenate([rgb[..., ::-1], np.zeros_like(g)[..., None]], -1))
        want = rgb / 255                                              # alpha dropped, the stored colour kept
    elif kind == "gray_alpha":
        Image.fromarray(np.stack([g, g], -1), "LA").save(f)
        want = np.repeat(g[..., None], 3, 2) / 255
    else:
        pal = Image.fromarray(rgb).convert("P", palette=Image.Palette.ADAPTIVE, colors=8)
        pal.save(f)
        want = np.asarray(pal.convert("RGB")) / 255
        assert np.array_equal(read_label_map(f), np.asarray(pal))  # a label map: the indices, not the colours
    got = read_rgb(f).permute(1, 2, 0).numpy()
    assert np.allclose(got, want, atol=1e-6)


def test_uint8_image_tensors_are_not_normalised_in_uint8():
    """Regression (issue 48): a base dataset of uint8 images gave a saturated (all-white) rotated panorama."""
    from omnidl.data.horizon import RotatedPanoramas
    from omnidl.data.readers import image_to_float
    img = torch.full((3, 16, 32), 128, dtype=torch.uint8)
    s = RotatedPanoramas([{"image": img}], height=16, width=32, augment=False, max_tilt_deg=0, deterministic=True)[0]
    assert float(s["image"].max()) == pytest.approx(128 / 255, abs=1e-3)
    assert torch.equal(image_to_float(img), img.float() / 255)
    with pytest.raises(TypeError, match="dtype torch.int64"):
        image_to_float(img.long())


# ============================================================================================ EXR
EXR_COMPRESSIONS = ["NO", "RLE", "ZIPS", "ZIP", "PIZ", "PXR24", "B44", "B44A", "DWAA", "DWAB"]


@pytest.mark.parametrize("comp", EXR_COMPRESSIONS + ["PIZ-tiled"])
def test_exr_every_compression(tmp_path, comp):
    """Regression (issue 49): PIZ / DWAA / ... files were refused; the OpenEXR package reads them all."""
    import OpenEXR
    from omnidl.data.exr import read_exr, read_exr_depth
    rng = np.random.default_rng(2)
    d = (rng.random((13, 21)) * 8 + 0.5).astype(np.float32)
    header = {"compression": getattr(OpenEXR, comp.split("-")[0] + "_COMPRESSION"), "type": OpenEXR.scanlineimage}
    if comp.endswith("tiled"):
        tiles = OpenEXR.TileDescription()
        tiles.xSize = tiles.ySize = 8
        header.update(type=OpenEXR.tiledimage, tiles=tiles)
    OpenEXR.File(header, {"Y": d, "H": d.astype(np.float16)}).write(str(tmp_path / "d.exr"))
    ref = OpenEXR.File(str(tmp_path / "d.exr"), separate_channels=True).channels()
    planes = read_exr(tmp_path / "d.exr")
    assert sorted(planes) == ["H", "Y"] and planes["H"].dtype == np.float16
    for name in ("Y", "H"):
        assert np.array_equal(planes[name], ref[name].pixels)       # what OpenEXR itself reads (lossy ones too)
    if comp in ("NO", "RLE", "ZIPS", "ZIP", "PIZ", "PIZ-tiled"):
        assert np.array_equal(read_exr_depth(tmp_path / "d.exr", "Y"), d)


def test_exr_without_the_package_names_it(tmp_path, monkeypatch):
    """Without OpenEXR the built-in reader refuses PIZ with a message naming the package to install."""
    import OpenEXR
    from omnidl.data import exr
    OpenEXR.File({"compression": OpenEXR.PIZ_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"Y": np.ones((4, 4), np.float32)}).write(str(tmp_path / "p.exr"))
    monkeypatch.setattr(exr, "_openexr", lambda: None)
    with pytest.raises(DataValidationError, match=r"p\.exr: EXR compression is PIZ.*pip install OpenEXR"):
        exr.read_exr(tmp_path / "p.exr")


def test_pano3d_reads_piz_views(tmp_path):
    import OpenEXR
    from omnidl.data.pano3d import Pano3D
    from tests.data.test_pano3d import write_views
    truth = write_views(tmp_path)
    for stem, (rgb, d) in truth.items():
        OpenEXR.File({"compression": OpenEXR.DWAA_COMPRESSION, "type": OpenEXR.scanlineimage},
                     {"Y": d}).write(str(tmp_path / "M3D" / f"{stem}_depth_0_Left_Down_0.0.exr"))
    s = Pano3D(tmp_path, split_file=tmp_path / "test.txt", height=None, width=None)[0]
    assert s["depth"].shape == (1, 16, 32) and s["meta"]["invalid_depth"] >= 4


@FEW
@given(nan=st.integers(0, 5), inf=st.integers(0, 5), unit=st.sampled_from([1.0, 1000.0, 100.0, 0.001]))
def test_exr_depth_nan_inf_and_units(tmp_path, nan, inf, unit):
    """Pano3D: NaN/inf are counted invalid pixels (never a silent value); a map in another unit is an error."""
    import OpenEXR
    from omnidl.data.pano3d import read_depth_exr
    rng = np.random.default_rng(nan * 7 + inf)
    d = (rng.random((8, 16)) * 6 + 0.5).astype(np.float32)
    flat = d.reshape(-1)
    flat[:nan] = np.nan
    flat[nan:nan + inf] = np.inf
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"Y": d * np.float32(unit)}).write(str(tmp_path / "d.exr"))
    if unit != 1.0:
        with pytest.raises(DataValidationError, match=r"d\.exr: EXR depth channel 'Y' is of median .*wrong unit"):
            read_depth_exr(tmp_path / "d.exr", 10.0)
        return
    depth, n_bad = read_depth_exr(tmp_path / "d.exr", 10.0)
    assert n_bad == nan + inf and np.isfinite(depth).all()
    ok = np.isfinite(d)
    assert np.array_equal(depth[ok], d[ok]) and (depth[~ok] == 0).all()


# ============================================================================================ Structured3D semantics
@pytest.mark.parametrize("mode", ["L", "P"])
def test_structured3d_semantic_palette_and_grayscale(tmp_path, mode):
    """Regression (issue 49): a palette semantic.png was refused; palette index = NYUv2-40 id, as grey values."""
    from omnidl.data.structured3d import Structured3D, nyu40_lut
    truth = write_structured3d(tmp_path, scenes=("scene_00000",))
    rgb, mm, sem = next(iter(truth.values()))
    p = tmp_path / "scene_00000/2D_rendering/485142/panorama/full/semantic.png"
    im = Image.fromarray(sem)
    if mode == "P":
        im = im.convert("P")
        im.putpalette([(7 * i) % 256 for i in range(768)])          # any colours: the index is the id
        im.putdata(sem.reshape(-1).tolist())
    im.save(p)
    assert Image.open(p).mode == mode
    s = Structured3D(tmp_path, split="train", height=None, width=None)[0]
    assert np.array_equal(s["semantic"].numpy(), nyu40_lut()[sem])


# ============================================================================================ label_cor
W, H = 128, 64


@st.composite
def convex_rooms(draw):
    """A convex room around the camera: K corners on a circle (centre offset), distinct columns >= 12 degrees."""
    k = draw(st.integers(3, 7))
    gaps = draw(st.lists(st.floats(12, 150), min_size=k, max_size=k))
    total = sum(gaps)
    assume(max(gaps) / total * 360 < 170)
    ang = np.cumsum(np.array(gaps) / total * 2 * math.pi) + draw(st.floats(0, 2 * math.pi))
    r = draw(st.floats(1.5, 4.0))
    c = np.array([draw(st.floats(-0.3, 0.3)), draw(st.floats(-0.3, 0.3))]) * r
    return c + r * np.stack([np.cos(ang), np.sin(ang)], -1)


def _label_cor(poly: np.ndarray) -> np.ndarray:
    from omnidl.metrics.layout_protocol import corner_pixels
    return corner_pixels(poly, (-1.6, 1.2), W, H).reshape(-1, 2) - 0.5


MUTATIONS = ["none", "roll", "reverse", "permute", "duplicate", "swap-ceiling-floor", "split-column", "scale"]


def _mutate(cor: np.ndarray, how: str, data) -> tuple[np.ndarray, bool]:
    """``(mutated label_cor, whether it still describes the same room)``."""
    pairs = cor.reshape(-1, 2, 2).copy()
    k = len(pairs)
    if how == "roll":
        return np.roll(pairs, data.draw(st.integers(1, k - 1)), 0).reshape(-1, 2), True
    if how == "reverse":
        return pairs[::-1].reshape(-1, 2), True
    if how == "permute":
        perm = np.array(data.draw(st.permutations(range(k))))
        same = any(np.array_equal(perm, np.roll(o, s)) for o in (np.arange(k), np.arange(k)[::-1]) for s in range(k))
        return pairs[perm].reshape(-1, 2), same
    if how == "duplicate":
        i = data.draw(st.integers(0, k - 1))
        return np.insert(pairs, i, pairs[i], 0).reshape(-1, 2), False
    if how == "swap-ceiling-floor":
        i = data.draw(st.integers(0, k - 1))
        pairs[i] = pairs[i, ::-1]
        return pairs.reshape(-1, 2), False
    if how == "split-column":
        i = data.draw(st.integers(0, k - 1))
        pairs[i, 0, 0] = (pairs[i, 0, 0] + data.draw(st.floats(W / 50, W / 8))) % W
        return pairs.reshape(-1, 2), False
    if how == "scale":
        return pairs.reshape(-1, 2) * data.draw(st.sampled_from([10.0, 100.0, 0.1])), False
    return pairs.reshape(-1, 2), True


def _same_room(corners_cam: torch.Tensor, n: int, poly: np.ndarray) -> bool:
    from omnidl.data.layout_sample import polygon_from_corners_cam
    got = polygon_from_corners_cam(corners_cam[:n].double().numpy())
    if len(got) != len(poly):
        return False
    d = np.linalg.norm(got[:, None] - poly[None], axis=-1)
    return bool((d.min(1) < 0.05).all() and (d.min(0) < 0.05).all())


def _write_cor(path: Path, cor: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(f"{x:.4f} {y:.4f}\n" for x, y in cor))


@PROPS
@given(poly=convex_rooms(), how=st.sampled_from(MUTATIONS), adapter=st.sampled_from(["horizonnet", "structured3d"]),
       data=st.data())
def test_label_cor_mutations_error_or_the_room(tmp_path_factory, poly, how, adapter, data):
    """Shuffled, duplicated, swapped, split-column or unit-scaled corners: a named error, or the same room."""
    cor, same = _mutate(_label_cor(poly), how, data)
    root = tmp_path_factory.mktemp(adapter)
    if adapter == "horizonnet":
        from omnidl.data.horizonnet_format import HorizonNetFolderDataset
        (root / "img").mkdir()
        cv2.imwrite(str(root / "img" / "a.png"), np.full((H, W, 3), 90, np.uint8))
        _write_cor(root / "label_cor" / "a.txt", cor)
        load = lambda: HorizonNetFolderDataset(root)[0]           # noqa: E731
        label = "a.txt"
    else:
        from omnidl.data.structured3d import Structured3D
        write_structured3d(root, scenes=("scene_00000",), w=W, h=H)
        _write_cor(root / "scene_00000/2D_rendering/485142/panorama/layout.txt", cor)
        load = lambda: Structured3D(root, split="train", layout=True, depth=False, semantic=False,  # noqa: E731
                                    height=None, width=None)[0]
        label = "layout.txt"
    if same:
        s = load()
        assert _same_room(s["corners_cam"], int(s["num_walls"]), poly)
        return
    try:
        s = load()
    except CorruptSampleError as e:
        assert label in str(e)
        return
    pytest.fail(f"{how}: a label_cor of another room loaded without an error "
                f"(num_walls={int(s['num_walls'])})")


# ============================================================================================ units
@FEW
@given(factor=st.sampled_from([1.0, 100.0, 1000.0, 0.01]), what=st.sampled_from(["all", "heights", "points"]))
def test_pano_annotator_units(tmp_path_factory, factor, what):
    """A PanoAnnotator file in centimetres / millimetres (all values, heights only or points only): a named error."""
    from omnidl.data.pano_annotator import read_pano_annotator_json
    root = tmp_path_factory.mktemp("pa")
    d = pano_annotator_label(ROOMS["ell"], 1.5, 1.3)
    if what in ("all", "heights"):
        for key in ("cameraHeight", "layoutHeight", "cameraCeilingHeight"):
            d[key] *= factor
    if what in ("all", "points"):
        for p in d["layoutPoints"]["points"]:
            p["xyz"] = [v * factor for v in p["xyz"]]
    f = root / "l.json"
    f.write_text(json.dumps(d))
    if factor == 1.0:
        lab = read_pano_annotator_json(f)
        assert np.allclose(lab.polygon, ROOMS["ell"]) and lab.camera_height == 1.5
        return
    if what == "points" and factor < 1:    # a room 6 cm across around a 1.5 m camera: valid geometry, not judged
        return
    with pytest.raises(DataValidationError, match=r"l\.json: .*(camera height|polygon|height) is .*expected"):
        read_pano_annotator_json(f)


@FEW
@given(factor=st.sampled_from([1.0, 1e4, 1e-3]))
def test_zind_units(tmp_path_factory, factor):
    """ZInD with a floor scale in the wrong unit: the panoramas are left out with a warning naming them."""
    from omnidl.data.zind import ZInD
    root = tmp_path_factory.mktemp("zind")
    write_zind(root, 64, 32, houses=("0000",), partition={"train": ["0000"]})
    p = root / "0000" / "zind_data.json"
    d = json.loads(p.read_text())
    d["scale_meters_per_coordinate"]["floor_01"] *= factor
    p.write_text(json.dumps(d))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            ds = ZInD(root, split="train", height=32, width=64)
        except FileNotFoundError as e:
            assert factor != 1.0 and "no usable panoramas" in str(e)
            assert any("camera height" in str(w.message) or "across" in str(w.message) for w in caught)
            return
    assert factor == 1.0 and len(ds) == 3 and not caught


@FEW
@given(in_metres=st.booleans(), dataset=st.sampled_from(["stanford", "matterport", "structured3d"]))
def test_depth_png_units(tmp_path_factory, in_metres, dataset):
    """A depth PNG holding whole metres where its format stores 1/512 m, 1/4000 m or millimetres: a named error,
    never a plausible-looking depth. (A finer unit than the format's saturates the 16 bits.)"""
    from tests.data.data_fixtures import write_matterport, write_stanford
    root = tmp_path_factory.mktemp(dataset)
    if dataset == "stanford":
        from omnidl.data.stanford2d3ds import DEPTH_SCALE, Stanford2D3DS
        write_stanford(root, areas=("1",), per_area=1, w=32, h=16)
        f = next((root / "area_1/pano/depth").iterdir())
        ds = lambda: Stanford2D3DS(str(root), areas=["1"], height=None, width=None)   # noqa: E731
    elif dataset == "matterport":
        from omnidl.data.matterport3d import DEPTH_SCALE, Matterport3D
        write_matterport(root, scenes=("scA",), per_scene=1, w=32, h=16, splits={"train": ["scA"]})
        f = root / "scA" / "pano00_depth.png"
        ds = lambda: Matterport3D(str(root), split="train", height=None, width=None)   # noqa: E731
    else:
        from omnidl.data.structured3d import DEPTH_SCALE, Structured3D
        write_structured3d(root, scenes=("scene_00000",), w=32, h=16)
        f = root / "scene_00000/2D_rendering/485142/panorama/full/depth.png"
        ds = lambda: Structured3D(root, split="train", height=None, width=None)   # noqa: E731
    if not in_metres:
        assert float(ds()[0]["depth"].max()) > 0
        return
    raw = cv2.imread(str(f), cv2.IMREAD_UNCHANGED).astype(np.float64)
    metres = np.where(raw == 65535, 0, np.round(raw / DEPTH_SCALE))
    cv2.imwrite(str(f), np.maximum(metres, 1).astype(np.uint16))
    with pytest.raises(DataValidationError, match=rf"{f.name}: depth map is of median .*wrong unit"):
        ds()[0]


# ============================================================================================ paths in dataset files
SEGMENT = st.text(alphabet="abcXYZ09_-.", min_size=1, max_size=6).filter(lambda s: s not in (".", ".."))


@PROPS
@given(parts=st.lists(st.one_of(SEGMENT, st.just("..")), min_size=1, max_size=4), absolute=st.booleans())
def test_paths_in_dataset_files_stay_in_the_root(tmp_path, parts, absolute):
    from omnidl.data.pano3d import read_pair_list
    from omnidl.data.splits import read_split_list
    rel = ("/" if absolute else "") + "/".join(parts)
    escapes = absolute or ".." in parts
    (tmp_path / "pairs.txt").write_text(f"ok/a.png ok/a.exr\n{rel} b.exr\n")
    (tmp_path / "split.txt").write_text(f"good\n{rel}\n")
    for reader, f in ((read_pair_list, "pairs.txt"), (read_split_list, "split.txt")):
        if escapes:
            with pytest.raises(DataValidationError, match=rf"{f}:2: path .* leaves the dataset root"):
                reader(tmp_path / f)
        else:
            assert len(reader(tmp_path / f)) == 2


def test_zind_image_path_cannot_escape(tmp_path):
    from omnidl.data.zind import ZInD
    write_zind(tmp_path, 64, 32)
    p = tmp_path / "0000" / "zind_data.json"
    d = json.loads(p.read_text())
    pano = d["merger"]["floor_01"]["complete_room_01"]["partial_room_01"]["pano_1"]
    pano["image_path"] = "../../../etc/passwd"
    p.write_text(json.dumps(d))
    with pytest.raises(DataValidationError, match=r"zind_data\.json: merger\..*pano_1\.image_path: path "
                                                  r"'\.\./\.\./\.\./etc/passwd' leaves the dataset root"):
        ZInD(tmp_path, split="train", height=32, width=64)


# ============================================================================================ messages
@pytest.mark.parametrize("dup_at", [1, 3])
def test_duplicate_point_is_not_called_self_intersecting(dup_at):
    """Regression (issue 48): a duplicated corner was reported as a self-intersecting polygon."""
    from omnidl.data.layout_sample import check_room
    box = ROOMS["box"]
    poly = np.insert(box, dup_at, box[dup_at - 1], 0) if dup_at < 4 else box
    with pytest.raises(DataValidationError, match=r"corner \d = .* repeating corner \d \(a duplicated point\)") as e:
        check_room(poly, "room.json", "layout")
    assert "self-intersecting" not in str(e.value)
