"""Bad dataset files, one table row each, with the verdict every loader must give (reliability findings §1).

Each row starts from a small valid dataset (written once per module, copied into ``tmp_path``), breaks one
file with a ``mutate(root)`` function, then loads it: ERROR rows call the dataset directly (the message must
name the file/field and what was expected), SKIP rows go through :class:`omnidl.data.robust.SkipCorrupt` (or
the loader's own init) and need a warning naming the file, OK rows check the value returned.
Row names start with ``f<N>`` for row N of the findings table (``reliability.md`` §1), ``x`` for extra rows.
"""
from __future__ import annotations

import json
import logging
import shutil
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from omnidl.data.robust import CorruptSampleError, SkipCorrupt, TooManyCorruptSamples
from tests.data.data_fixtures import truncate, write_matterport, write_stanford
from tests.robustness.verdicts import ERROR, OK, SKIP, expect, row

W, H = 64, 32


class _LogToWarnings(logging.Handler):
    """SkipCorrupt and the loaders' init report skips on the ``omnidl.data`` logger; SKIP rows need warnings."""

    def emit(self, record):
        if record.levelno >= logging.WARNING:
            warnings.warn(record.getMessage())


def flagged(fn):
    """``fn`` with the ``omnidl.data`` warnings re-emitted as Python warnings (for :func:`expect`)."""
    def run():
        logger, handler = logging.getLogger("omnidl.data"), _LogToWarnings()
        logger.addHandler(handler)
        try:
            return fn()
        finally:
            logger.removeHandler(handler)
    return run


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def zero(path: Path) -> None:
    path.write_bytes(b"")


def flip_bytes(path: Path) -> None:
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 40] = bytes(255 - b for b in data[mid:mid + 40])
    path.write_bytes(bytes(data))


def one(pattern_dir: Path, glob: str) -> Path:
    return sorted(pattern_dir.glob(glob))[0]


# =================================================================================================
# Stanford2D3DS (findings 1-22) and the shared readers
# =================================================================================================

@pytest.fixture(scope="module")
def stanford_base(tmp_path_factory):
    root = tmp_path_factory.mktemp("stanford")
    write_stanford(root, areas=("1",), per_area=2, w=W, h=H)
    return root


def _rgb(root):
    return one(root / "area_1/pano/rgb", "*_rgb.png")


def _depth(root):
    return one(root / "area_1/pano/depth", "*_depth.png")


def _sem(root):
    return one(root / "area_1/pano/semantic", "*_semantic.png")


def _stanford(root, **kw):
    from omnidl.data.stanford2d3ds import Stanford2D3DS
    return Stanford2D3DS(str(root), areas=["1"], height=None, width=None, **kw)


def _reencode_rgb(root, convert):
    p = _rgb(root)
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(p), convert(img))
    return img


def _ok_gray(root):
    p = _rgb(root)
    gray = cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2GRAY)
    cv2.imwrite(str(p), gray)
    s = _stanford(root)[0]
    assert s["image"].shape == (3, H, W)
    assert torch.equal(s["image"][0], s["image"][1]) and torch.equal(s["image"][1], s["image"][2])
    assert torch.allclose(s["image"][0] * 255, torch.from_numpy(gray).float())


def _ok_16bit(root):
    img = _reencode_rgb(root, lambda a: a.astype(np.uint16) * 257)
    s = _stanford(root)[0]
    assert torch.allclose(s["image"] * 255, torch.from_numpy(img[..., ::-1].copy()).permute(2, 0, 1).float())


def _ok_rgba(root):
    img = _reencode_rgb(root, lambda a: np.concatenate([a, np.full(a.shape[:2] + (1,), 7, np.uint8)], -1))
    s = _stanford(root)[0]
    assert s["image"].shape == (3, H, W)
    assert torch.allclose(s["image"] * 255, torch.from_numpy(img[..., ::-1].copy()).permute(2, 0, 1).float())


def _ok_depth_3ch(root):
    p = _depth(root)
    d = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(p), np.stack([d, d // 2, d // 3], -1))
    got = _stanford(root)[0]["depth"][0].numpy()
    assert np.allclose(got, np.where(d == 65535, 0, d / 512.0), atol=1e-5)


def _ok_depth_missing_value(root):
    cv2.imwrite(str(_depth(root)), np.full((H, W), 65535, np.uint16))
    assert float(_stanford(root)[0]["depth"].abs().max()) == 0.0


def _ok_sem_out_of_list(root):
    idx = 500  # beyond the 6 labels of the list: documented as unknown (0)
    cv2.imwrite(str(_sem(root)), np.full((H, W, 3), [idx % 256, idx // 256, 0], np.uint8))
    assert int(_stanford(root)[0]["semantic"].abs().max()) == 0


def _ok_non_utf8(root):
    bad = b"\xff\xfe".decode("utf-8", "surrogateescape")
    for sub, suffix in (("rgb", "rgb"), ("depth", "depth"), ("semantic", "semantic")):
        p = one(root / "area_1/pano" / sub, f"*_{suffix}.png")
        p.rename(p.with_name(f"camera_{bad}_x_{suffix}.png"))
    ds = _stanford(root)
    assert len(ds) == 2 and all(ds[i]["image"].shape == (3, H, W) for i in range(2))


def _ok_odd_size(root):
    for i, p in enumerate(sorted((root / "area_1/pano/rgb").glob("*.png"))):
        stem = p.name[: -len("_rgb.png")]
        cv2.imwrite(str(p), np.full((31, 63, 3), 9, np.uint8))
        cv2.imwrite(str(root / "area_1/pano/depth" / f"{stem}_depth.png"), np.full((31, 63), 1024, np.uint16))
        cv2.imwrite(str(root / "area_1/pano/semantic" / f"{stem}_semantic.png"), np.ones((31, 63, 3), np.uint8))
    s = _stanford(root)[0]
    assert s["image"].shape == (3, 31, 63) and torch.allclose(s["depth"], torch.full((1, 31, 63), 2.0))


def _ok_resized(root):
    from omnidl.data.stanford2d3ds import Stanford2D3DS
    s = Stanford2D3DS(str(root), areas=["1"], height=16, width=32)[0]
    assert s["image"].shape == (3, 16, 32) and s["depth"].shape == (1, 16, 32) and s["semantic"].shape == (16, 32)


def _write_labels(root, text):
    (root / "assets" / "semantic_labels.json").write_text(text)


STANFORD_ROWS = [
    # (mutation, call: "item" = ds[0] direct, "skip" = SkipCorrupt(ds)[0], "init" = constructing it)
    row("f1-rgb-truncated", lambda r: truncate(_rgb(r)), "skip", verdict=SKIP,
        match=r"skipping sample 0: .*(truncated|cannot decode).*_rgb\.png"),
    row("f2-rgb-zero-byte", lambda r: zero(_rgb(r)), "skip", verdict=SKIP, match=r"empty file .*_rgb\.png"),
    row("f3-rgb-bytes-flipped", lambda r: flip_bytes(_rgb(r)), "skip", verdict=SKIP,
        match=r"cannot decode image .*_rgb\.png"),
    row("f4-rgb-smaller-than-depth", lambda r: cv2.imwrite(str(_rgb(r)), np.zeros((16, 32, 3), np.uint8)), "skip",
        verdict=SKIP, match=r"_depth\.png: depth map is 64x32, expected 32x16"),
    row("f5-rgb-grayscale", _ok_gray, None, verdict=OK),
    row("f6-rgb-16bit", _ok_16bit, None, verdict=OK),
    row("f7-rgba", _ok_rgba, None, verdict=OK),
    row("f8-depth-truncated", lambda r: truncate(_depth(r)), "skip", verdict=SKIP,
        match=r"(truncated|cannot decode).*_depth\.png"),
    row("f9-depth-zero-byte", lambda r: zero(_depth(r)), "skip", verdict=SKIP, match=r"empty file .*_depth\.png"),
    row("f10-depth-wrong-size", lambda r: cv2.imwrite(str(_depth(r)), np.ones((10, 20), np.uint16)), "item",
        verdict=ERROR, match=r"_depth\.png: depth map is 20x10, expected 64x32"),
    row("f11-depth-missing", lambda r: _depth(r).unlink(), "init", verdict=SKIP,
        match=r"skipping 1 sample.*missing label files.*_depth\.png"),
    row("f12-depth-8bit", lambda r: cv2.imwrite(str(_depth(r)), np.full((H, W), 200, np.uint8)), "item",
        verdict=ERROR, match=r"_depth\.png: depth map is 64x32 1-channel uint8, expected pixel type uint16"),
    row("f12b-depth-8bit-skipped", lambda r: cv2.imwrite(str(_depth(r)), np.full((H, W), 200, np.uint8)), "skip",
        verdict=SKIP, match=r"skipping sample 0: .*_depth\.png.*uint8.*uint16"),
    row("f13-depth-3ch-16bit", _ok_depth_3ch, None, verdict=OK),
    row("f14-depth-all-missing", _ok_depth_missing_value, None, verdict=OK),
    row("f15-semantic-missing", lambda r: _sem(r).unlink(), "init", verdict=SKIP,
        match=r"missing label files.*_semantic\.png"),
    row("f16-semantic-index-beyond-list", _ok_sem_out_of_list, None, verdict=OK),
    row("f17-semantic-single-channel", lambda r: cv2.imwrite(str(_sem(r)), np.zeros((H, W), np.uint8)), "skip",
        verdict=SKIP, match=r"_semantic\.png: semantic map is 64x32 1-channel uint8, expected a 3-channel"),
    row("f18-semantic-truncated", lambda r: truncate(_sem(r)), "skip", verdict=SKIP,
        match=r"(truncated|cannot decode).*_semantic\.png"),
    row("f19-labels-json-truncated", lambda r: _write_labels(r, '["<UNK>_0_<UNK>_0_0", "wal'), "init",
        verdict=ERROR, match=r"cannot read the label list .*semantic_labels\.json"),
    row("f20-labels-json-missing", lambda r: (r / "assets" / "semantic_labels.json").unlink(), "init",
        verdict=ERROR, match=r"semantic_labels\.json.*labels_json"),
    row("f21-non-utf8-names", _ok_non_utf8, None, verdict=OK),
    row("f22-empty-folders", lambda r: [p.unlink() for p in (r / "area_1/pano").rglob("*.png")], "init",
        verdict=ERROR, match=r"no \*_rgb\.png panoramas under"),
    row("x-semantic-16bit", lambda r: cv2.imwrite(str(_sem(r)), np.zeros((H, W, 3), np.uint16)), "item",
        verdict=ERROR, match=r"_semantic\.png: semantic map is .*uint16, expected pixel type uint8"),
    row("x-semantic-wrong-size", lambda r: cv2.imwrite(str(_sem(r)), np.zeros((8, 16, 3), np.uint8)), "item",
        verdict=ERROR, match=r"_semantic\.png: semantic map is 16x8, expected 64x32"),
    row("x-rgb-text-file", lambda r: _rgb(r).write_text("version https://git-lfs.github.com/spec/v1\n"), "item",
        verdict=ERROR, match=r"cannot decode image .*_rgb\.png"),
    row("x-odd-size-63x31", _ok_odd_size, None, verdict=OK),
    row("x-resized-output", _ok_resized, None, verdict=OK),
]


def _ok_rgb_exif(root):
    p = _rgb(root)
    up = cv2.imread(str(p))[..., ::-1].copy()
    p.write_bytes(_exif_pil(np.ascontiguousarray(up[::-1, ::-1]), 3))
    s = _stanford(root)[0]
    assert torch.allclose(s["image"], torch.from_numpy(up).permute(2, 0, 1).float() / 255)


STANFORD_ROWS += [
    row("x-depth-in-metres-not-512ths", lambda r: cv2.imwrite(str(_depth(r)), np.full((H, W), 3, np.uint16)), "item",
        verdict=ERROR, match=r"_depth\.png: depth map is of median 0\.00585938 m .*wrong unit"),
    row("x-rgb-exif-upside-down", _ok_rgb_exif, None, verdict=OK),
]


@pytest.mark.parametrize("mutate, call, verdict, match", STANFORD_ROWS)
def test_stanford2d3ds(stanford_base, tmp_path, mutate, call, verdict, match):
    root = _copy(stanford_base, tmp_path / "s")
    if call is None:                                   # OK rows check inside the mutation
        expect(lambda: mutate(root), verdict, match)
        return
    mutate(root)
    if call == "init":
        ds = expect(flagged(lambda: _stanford(root)), verdict, match)
        if verdict == SKIP:
            assert len(ds) == 1
        return
    ds = _stanford(root)
    if call == "skip":
        assert expect(flagged(lambda: SkipCorrupt(ds)[0]), verdict, match) is None
        assert SkipCorrupt(ds)[1] is not None          # the other sample still loads
    else:
        expect(lambda: ds[0], verdict, match, error=CorruptSampleError)


# =================================================================================================
# Image folder (23-26) and Matterport3D (61-64)
# =================================================================================================

def _folder(root):
    from omnidl.data.folder import ImageFolder
    return ImageFolder(str(root), height=None, width=None)


def _jpg(root, truncate_to=None):
    cv2.imwrite(str(root / "b.jpg"), np.random.default_rng(0).integers(0, 255, (H, W, 3), dtype=np.uint8))
    if truncate_to is not None:
        truncate(root / "b.jpg", truncate_to)


FOLDER_ROWS = [
    row("f23-jpg-truncated", lambda r: _jpg(r, 0.6), verdict=SKIP, match=r"(truncated|cannot decode).*b\.jpg"),
    row("f24-jpg-zero-byte", lambda r: (r / "b.jpg").write_bytes(b""), verdict=SKIP, match=r"empty file .*b\.jpg"),
    row("f25-text-named-png", lambda r: (r / "b.png").write_text("hello"), verdict=SKIP,
        match=r"cannot decode image .*b\.png"),
    row("f26-empty-folder", None, verdict=ERROR, match=r"holds no images with extensions"),
    row("x-folder-rgba-and-gray", "ok", verdict=OK),
]


@pytest.mark.parametrize("mutate, verdict, match", FOLDER_ROWS)
def test_image_folder(tmp_path, mutate, verdict, match):
    if mutate is None:
        expect(lambda: _folder(tmp_path), verdict, match)
        return
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((H, W, 3), np.uint8))
    if mutate == "ok":
        cv2.imwrite(str(tmp_path / "c.png"), np.zeros((H, W, 4), np.uint8))
        cv2.imwrite(str(tmp_path / "d.png"), np.zeros((H, W), np.uint16))
        ds = _folder(tmp_path)
        assert all(ds[i]["image"].shape == (3, H, W) for i in range(3))
        return
    mutate(tmp_path)
    ds = SkipCorrupt(_folder(tmp_path))
    assert ds[0] is not None
    assert expect(flagged(lambda: ds[1]), verdict, match) is None


@pytest.fixture(scope="module")
def matterport_base(tmp_path_factory):
    root = tmp_path_factory.mktemp("mp3d")
    write_matterport(root, scenes=("scA",), per_scene=2, w=W, h=H, splits={"train": ["scA"]})
    return root


def _mp(root, **kw):
    from omnidl.data.matterport3d import Matterport3D
    return Matterport3D(str(root), split="train", height=None, width=None, semantic=True, **kw)


def _ok_mp_16bit(root):
    p = root / "scA" / "pano00_semantic.png"
    sem = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(p), sem.astype(np.uint16))
    assert torch.equal(_mp(root)[0]["semantic"], torch.from_numpy(sem.astype(np.int64)))


MATTERPORT_ROWS = [
    row("f61-semantic-id-200",
        lambda r: cv2.imwrite(str(r / "scA/pano00_semantic.png"), np.full((H, W), 200, np.uint8)), "item",
        verdict=ERROR, match=r"pano00_semantic\.png: semantic map is class id\(s\) \[200\].*expected ids 0\.\.13"),
    row("f62-semantic-16bit", _ok_mp_16bit, None, verdict=OK),
    row("f63-split-lists-missing-scene", lambda r: (r / "scenes_train.txt").write_text("scA\nsceneZ\n"), "init",
        verdict=ERROR, match=r"lacks \['sceneZ'\]"),
    row("f64-split-file-empty", lambda r: (r / "scenes_train.txt").write_text(""), "init", verdict=ERROR,
        match=r"no \*_rgb\.png panoramas in the scene folders \[\]"),
    row("x-depth-8bit", lambda r: cv2.imwrite(str(r / "scA/pano00_depth.png"), np.ones((H, W), np.uint8)), "item",
        verdict=ERROR, match=r"pano00_depth\.png: depth map .*uint8, expected pixel type uint16"),
    row("x-semantic-3ch", lambda r: cv2.imwrite(str(r / "scA/pano00_semantic.png"), np.ones((H, W, 3), np.uint8)),
        "item", verdict=ERROR, match=r"pano00_semantic\.png: semantic map is .*3-channel.*expected a single-channel"),
    row("x-semantic-missing", lambda r: (r / "scA/pano00_semantic.png").unlink(), "init", verdict=SKIP,
        match=r"missing label files.*pano00_semantic\.png"),
]


def _ok_mp_palette(root):
    from PIL import Image
    p = root / "scA" / "pano00_semantic.png"
    ids = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    im = Image.fromarray(ids).convert("P")
    im.putpalette([(37 * i) % 256 for i in range(768)])
    im.putdata(ids.reshape(-1).tolist())
    im.save(p)
    assert torch.equal(_mp(root)[0]["semantic"], torch.from_numpy(ids.astype(np.int64)))


MATTERPORT_ROWS += [
    row("x-semantic-palette-indices", _ok_mp_palette, None, verdict=OK),
    row("x-scenes-file-escapes", lambda r: (r / "scenes_train.txt").write_text("scA\n../outside\n"), "init",
        verdict=ERROR, match=r"scenes_train\.txt:2: path '\.\./outside' leaves the dataset root"),
]


@pytest.mark.parametrize("mutate, call, verdict, match", MATTERPORT_ROWS)
def test_matterport3d(matterport_base, tmp_path, mutate, call, verdict, match):
    root = _copy(matterport_base, tmp_path / "m")
    if call is None:
        expect(lambda: mutate(root), verdict, match)
        return
    mutate(root)
    if call == "init":
        expect(flagged(lambda: _mp(root)), verdict, match)
        return
    ds = _mp(root)
    expect(lambda: ds[0], verdict, match, error=CorruptSampleError)
    assert SkipCorrupt(ds)[0] is None                  # and training skips it


# =================================================================================================
# HorizonNet label_cor folder (27-41)
# =================================================================================================

#: 4 corners of a 64x32 panorama (ceiling then floor of each), pixel centres at integers
GOOD_COR = np.array([[5, 10], [5, 22], [20, 11], [20, 21], [37, 10], [37, 22], [52, 11], [52, 21]], float)


def _write_cor(path: Path, rows) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(f"{x} {y}\n" for x, y in rows))


@pytest.fixture(scope="module")
def horizonnet_base(tmp_path_factory):
    root = tmp_path_factory.mktemp("hn")
    (root / "img").mkdir()
    for name in ("a", "b"):
        cv2.imwrite(str(root / "img" / f"{name}.png"), np.full((H, W, 3), 90, np.uint8))
        _write_cor(root / "label_cor" / f"{name}.txt", GOOD_COR)
    return root


def _hn(root, **kw):
    from omnidl.data.horizonnet_format import HorizonNetFolderDataset
    return HorizonNetFolderDataset(str(root), **kw)


def _cor(root, rows):
    _write_cor(root / "label_cor" / "a.txt", rows)


def _ok_hn(root, transform=None, check=None):
    if transform is not None:
        p = root / "img" / "a.png"
        cv2.imwrite(str(p), transform(cv2.imread(str(p))))
    s = _hn(root)[0]
    assert s["image"].shape == (3, H, W)
    assert 0 < float(s["corner_heat"].min()) and float(s["corner_heat"].max()) <= 1.0
    assert torch.isfinite(s["corners_cam"]).all() and bool(s["boundary_valid"].all())
    if check is not None:
        check(s)


def _ok_below_horizon(root):
    rows = GOOD_COR.copy()
    rows[1, 1] = H / 2 - 0.5 + 0.4          # floor 0.4 px below the horizon: far, but geometrically consistent
    _cor(root, rows)
    s = _hn(root)[0]
    assert torch.isfinite(s["corners_cam"]).all() and float(s["corners_cam"].abs().max()) > 20


def _ok_edges(root):
    rows = GOOD_COR.copy()                  # a room (corners in wall order around the camera) touching the edges
    rows[0, 0] = rows[1, 0] = -0.5          # a corner on the seam: the image spans [-0.5, W - 0.5]
    rows[6, 0] = rows[7, 0] = W - 0.01      # [0, W) tools: 0.49 px past the seam = column -0.01 on the circle
    rows[2, 1] = 0.0                        # y of [0, H) tools (a tall room); the floor stays off the nadir
    _cor(root, rows)
    s = _hn(root)[0]
    heat = s["corner_heat"][0]
    assert float(heat.max()) <= 1.0 and float(heat[-1]) == pytest.approx(0.96 ** 0.5)
    assert float(heat[0]) == pytest.approx(0.96 ** 0.01, abs=1e-6)      # the wrapped corner at u = 0.49


def _ok_resized_labels(root):
    s = _hn(root, width=128, height=64)[0]
    assert s["image"].shape == (3, 64, 128) and float(s["corner_heat"].max()) <= 1.0
    assert float(s["corner_heat"][0, 10]) == pytest.approx(1.0, abs=1e-6)   # x=5 at 64 px -> column 10.5 at 128


HORIZONNET_ROWS = [
    row("f27-img-truncated", lambda r: truncate(r / "img/a.png"), verdict=ERROR,
        match=r"(truncated|cannot decode).*img/a\.png"),
    row("f27b-img-truncated-skipped", lambda r: truncate(r / "img/a.png"), verdict=SKIP,
        match=r"skipping sample 0: .*img/a\.png"),
    row("f28-img-zero-byte", lambda r: zero(r / "img/a.png"), verdict=ERROR, match=r"empty file .*img/a\.png"),
    row("f29-label-missing", lambda r: (r / "label_cor/a.txt").unlink(), verdict=ERROR,
        match=r"a\.png: no label file .*label_cor/a\.txt"),
    row("f30-odd-line-count", lambda r: _cor(r, GOOD_COR[:7]), verdict=ERROR, match=r"a\.txt: 7 points.*pairs"),
    row("f31-not-numbers", lambda r: (r / "label_cor/a.txt").write_text("5 10\nabc def\n"), verdict=ERROR,
        match=r"a\.txt:2: not numbers: 'abc def'"),
    row("f32-empty-file", lambda r: (r / "label_cor/a.txt").write_text(""), verdict=ERROR,
        match=r"a\.txt: label_cor is empty \(0 points\), expected ceiling/floor pairs"),
    row("f33-one-wall", lambda r: _cor(r, GOOD_COR[:2]), verdict=ERROR,
        match=r"a\.txt: label_cor is 1 corner\(s\).*expected at least 3 corners"),
    row("f34-x-1000", lambda r: _cor(r, np.where([[1, 0]] * 8, GOOD_COR + 1000, GOOD_COR)), verdict=ERROR,
        match=r"a\.txt: label_cor x is 1005 .*expected values in \[-0\.5, 64\)"),
    row("f34b-x-minus-5", lambda r: _cor(r, [[-5, 10], [-5, 22]] + GOOD_COR[2:].tolist()), verdict=ERROR,
        match=r"a\.txt: label_cor x is -5 .*expected values in \[-0\.5, 64\)"),
    row("f35-floor-y-500", lambda r: _cor(r, [[5, 10], [5, 500]] + GOOD_COR[2:].tolist()), verdict=ERROR,
        match=r"a\.txt: label_cor y is 500 .*expected values in \[-0\.5, 32\)"),
    row("f36-floor-just-below-horizon", _ok_below_horizon, verdict=OK),
    row("f37-nan", lambda r: (r / "label_cor/a.txt").write_text("nan 10\n5 22\n20 11\n20 21\n37 10\n37 22\n"),
        verdict=ERROR, match=r"a\.txt: label_cor is nan at index \(0, 0\).*expected finite"),
    row("f37b-inf", lambda r: (r / "label_cor/a.txt").write_text("5 10\n5 inf\n20 11\n20 21\n37 10\n37 22\n"),
        verdict=ERROR, match=r"a\.txt: label_cor is inf .*expected finite"),
    row("f38-ceiling-floor-swapped", lambda r: _cor(r, GOOD_COR[[1, 0, 3, 2, 5, 4, 7, 6]]),
        verdict=ERROR, match=r"a\.txt: label_cor is corner 0 with ceiling y=22 and floor y=10.*above"),
    row("f39-binary-bytes", lambda r: (r / "label_cor/a.txt").write_bytes(bytes(range(128, 256))), verdict=ERROR,
        match=r"cannot read .*a\.txt \(label_cor: not UTF-8 text"),
    row("f40-one-column", lambda r: _cor(r, [[5, 10], [5, 22]] * 4), verdict=ERROR,
        match=r"a\.txt: label_cor is 4 corner\(s\) in 1 distinct column"),
    row("f41-empty-img-folder", "empty", verdict=ERROR, match=r"no images in .*img"),
    row("x-three-fields", lambda r: (r / "label_cor/a.txt").write_text("5 10 3\n"), verdict=ERROR,
        match=r"a\.txt:1: expected 'x y'"),
    row("x-above-horizon-floor", lambda r: _cor(r, [[5, 10], [5, 14]] + GOOD_COR[2:].tolist()), verdict=ERROR,
        match=r"a\.txt: label_cor: every ceiling point must be above"),
    row("x-img-grayscale", lambda r: _ok_hn(r, lambda a: cv2.cvtColor(a, cv2.COLOR_BGR2GRAY)), verdict=OK),
    row("x-img-16bit", lambda r: _ok_hn(r, lambda a: a.astype(np.uint16) * 257,
                                        lambda s: pytest.approx(90 / 255) == float(s["image"].mean())), verdict=OK),
    row("x-img-rgba", lambda r: _ok_hn(r, lambda a: np.concatenate([a, a[..., :1]], -1)), verdict=OK),
    row("x-corners-on-image-edges", _ok_edges, verdict=OK),
    row("x-resized-labels-scaled", _ok_resized_labels, verdict=OK),
]


def _exif_pil(arr_rgb: np.ndarray, orientation: int) -> bytes:
    import io
    from PIL import Image
    ex = Image.Exif()
    ex[0x0112] = orientation
    b = io.BytesIO()
    Image.fromarray(arr_rgb).save(b, "PNG", exif=ex)
    return b.getvalue()


def _ok_hn_exif(root):
    up = np.full((H, W, 3), 90, np.uint8)
    up[: H // 4] = 250                                   # bright ceiling rows on top when upright
    (root / "img" / "a.png").write_bytes(_exif_pil(np.ascontiguousarray(up[::-1, ::-1]), 3))
    s = _hn(root)[0]
    assert torch.allclose(s["image"], torch.from_numpy(up).permute(2, 0, 1).float() / 255)


def _huge_png(path: Path) -> None:
    import struct
    import zlib

    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 60000, 30000, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"\0" * 16)) + chunk(b"IEND", b""))


def _split(rows):
    rows = np.array(rows, float)
    rows[2, 0] += 3.0                                    # corner 1's ceiling 3 columns off its floor (W/100 = 0.64)
    return rows


HORIZONNET_ROWS += [
    row("x-corners-out-of-order", lambda r: _cor(r, GOOD_COR[[0, 1, 4, 5, 2, 3, 6, 7]]), verdict=ERROR,
        match=r"a\.txt: label_cor \(top view of the floor corners\) is a self-intersecting polygon"),
    row("x-corner-duplicated", lambda r: _cor(r, np.concatenate([GOOD_COR, GOOD_COR[2:4]])), verdict=ERROR,
        match=r"a\.txt: label_cor is corner 4 at x=20 repeating corner 1, expected each corner once"),
    row("x-ceiling-floor-columns-differ", lambda r: _cor(r, _split(GOOD_COR)), verdict=ERROR,
        match=r"a\.txt: label_cor is corner 1 with ceiling x=23 and floor x=20, expected .* in one column"),
    row("x-room-over-100-m", lambda r: _cor(r, np.where([[0, 0], [0, 1]] * 4, 15.7, GOOD_COR)), verdict=ERROR,
        match=r"a\.txt: label_cor room (polygon|height) is [\d.]+ m.*expected (a room )?at most 100 m"),
    row("x-img-exif-upside-down", _ok_hn_exif, verdict=OK),
    row("x-img-over-pixel-limit-skipped", lambda r: _huge_png(r / "img/a.png"), verdict=SKIP,
        match=r"skipping sample 0: image .*img/a\.png \(image\) has more pixels than OpenCV decodes"),
]


@pytest.mark.parametrize("mutate, verdict, match", HORIZONNET_ROWS)
def test_horizonnet_folder(horizonnet_base, tmp_path, mutate, verdict, match):
    root = _copy(horizonnet_base, tmp_path / "h")
    if mutate == "empty":
        for p in (root / "img").iterdir():
            p.unlink()
        expect(lambda: _hn(root), verdict, match, error=FileNotFoundError)
        return
    if verdict == OK:
        expect(lambda: mutate(root), verdict, match)
        return
    mutate(root)
    if verdict == SKIP:
        assert expect(flagged(lambda: SkipCorrupt(_hn(root))[0]), verdict, match) is None
        return
    expect(lambda: _hn(root)[0], verdict, match)
    if (root / "label_cor/a.txt").exists():
        assert _hn(root)[1]["num_walls"] == 4              # the other sample is fine


# =================================================================================================
# NonCentralIndoorDataset (42-60) and its image + label_cor-only mode
# =================================================================================================

NAME = "SYN00000_R10000"


@pytest.fixture(scope="module")
def noncentral_base(tmp_path_factory):
    from omnidl.data.synthetic import SyntheticPanoramaDataset
    from omnidl.synth.export import sample_name, write_sample
    root = tmp_path_factory.mktemp("nc")
    sample = SyntheticPanoramaDataset(camera="noncentral_pano", width=W, height=H, rc=1.0, length=1,
                                      furniture=False)[0]
    assert sample_name("noncentral", 0, 1.0) == NAME
    write_sample(root, "noncentral", NAME, sample)
    return root


def _nc(root, **kw):
    from omnidl.data.noncentral_indoor import NonCentralIndoorDataset
    return NonCentralIndoorDataset(root, **kw)


def _f(root, *parts):
    return root.joinpath(*parts[:-1], parts[-1].replace("N", NAME, 1))


def _npy(root, folder, value):
    np.save(_f(root, "DataPython", folder, "N.npy"), value)


def _nan_at(root, folder, index):
    a = np.load(_f(root, "DataPython", folder, "N.npy")).astype(float)
    a[index] = np.nan
    _npy(root, folder, a)


def _ok_nc(root, transform=None):
    if transform is not None:
        p = _f(root, "img", "N.png")
        cv2.imwrite(str(p), transform(cv2.imread(str(p))))
    s = _nc(root)[0]
    assert s["image"].shape == (3, H, W) and s["depth"].shape == (1, H, W) and s["edges"].shape == (1, H, W)
    assert all(torch.isfinite(s[k]).all() for k in ("corners_cam", "boundary", "corner_heat", "depth"))


def _label_cor_only(root):
    for d in ("depth_coded", "EM_gt", "DataPython/3D_gt", "DataPython/cam_pose", "DataPython/label_ang"):
        shutil.rmtree(root / d)
    full = None
    s = _nc(root, label_cor_only=True)[0]
    assert set(s) >= {"image", "boundary", "boundary_valid", "corner_heat", "corners_cam", "num_walls", "meta"}
    assert "depth" not in s and "edges" not in s and full is None
    assert bool(s["boundary_valid"].all()) and float(s["corner_heat"].max()) <= 1.0


NONCENTRAL_ROWS = [
    row("f42-img-truncated", lambda r: truncate(_f(r, "img", "N.png")), verdict=ERROR,
        match=r"(truncated|cannot decode).*img/SYN00000_R10000\.png"),
    row("f43-img-zero-byte", lambda r: zero(_f(r, "img", "N.png")), verdict=ERROR,
        match=r"empty file .*img/SYN00000_R10000\.png"),
    row("f44-depth-coded-truncated", lambda r: truncate(_f(r, "depth_coded", "N.png")), verdict=ERROR,
        match=r"(truncated|cannot decode).*depth_coded/SYN00000_R10000\.png"),
    row("f45-depth-coded-zero-byte", lambda r: zero(_f(r, "depth_coded", "N.png")), verdict=ERROR,
        match=r"empty file .*depth_coded/SYN00000_R10000\.png"),
    row("f46-depth-coded-half-size", lambda r: cv2.imwrite(str(_f(r, "depth_coded", "N.png")),
                                                           np.ones((H // 2, W // 2, 3), np.uint8)), verdict=ERROR,
        match=r"depth_coded/SYN00000_R10000\.png: depth_coded is 32x16, expected 64x32"),
    row("f47-depth-coded-grayscale", lambda r: cv2.imwrite(str(_f(r, "depth_coded", "N.png")),
                                                           np.ones((H, W), np.uint8)), verdict=ERROR,
        match=r"depth_coded/SYN00000_R10000\.png: depth_coded is 64x32 1-channel uint8, expected a 3-channel"),
    row("f48-em-truncated", lambda r: truncate(_f(r, "EM_gt", "N.png")), verdict=ERROR,
        match=r"(truncated|cannot decode).*EM_gt/SYN00000_R10000\.png"),
    row("f49-em-half-size", lambda r: cv2.imwrite(str(_f(r, "EM_gt", "N.png")), np.zeros((H // 2, W // 2), np.uint8)),
        verdict=ERROR, match=r"EM_gt/SYN00000_R10000\.png: EM_gt is 32x16, expected 64x32"),
    row("f50-label-cor-missing", lambda r: _f(r, "DataPython", "label_cor", "N.txt").unlink(), verdict=ERROR,
        match=r"missing file .*label_cor/SYN00000_R10000\.txt"),
    row("f51-label-cor-odd-lines", lambda r: _write_cor(_f(r, "DataPython", "label_cor", "N.txt"), GOOD_COR[:5]),
        verdict=ERROR, match=r"SYN00000_R10000\.txt: 5 points.*even count"),
    row("f52-label-cor-x-out-of-range",
        lambda r: _write_cor(_f(r, "DataPython", "label_cor", "N.txt"), GOOD_COR + [[1000, 0]]), verdict=ERROR,
        match=r"SYN00000_R10000\.txt: label_cor x is 1005 .*expected values in \[-0\.5, 64\)"),
    row("f53-3d-gt-truncated", lambda r: truncate(_f(r, "DataPython", "3D_gt", "N.npy"), 0.8), verdict=ERROR,
        match=r"cannot read .*3D_gt/SYN00000_R10000\.npy \(3D_gt: .*complete numeric \.npy"),
    row("f54-3d-gt-nan", lambda r: _nan_at(r, "3D_gt", (1, 2)), verdict=ERROR,
        match=r"3D_gt/SYN00000_R10000\.npy: 3D_gt is nan at index \(1, 2\).*expected finite"),
    row("f55-3d-gt-odd-rows", lambda r: _npy(r, "3D_gt", np.ones((13, 3))), verdict=ERROR,
        match=r"3D_gt/SYN00000_R10000\.npy: 3D_gt is of shape \(13, 3\), expected shape \(2N, 3\)"),
    row("f56-cam-pose-2-values", lambda r: _npy(r, "cam_pose", np.zeros(2)), verdict=ERROR,
        match=r"cam_pose/SYN00000_R10000\.npy: cam_pose is 2 values, expected 3 values"),
    row("f57-label-ang-wrong-shape", lambda r: _npy(r, "label_ang", np.zeros((2, 10))), verdict=ERROR,
        match=r"label_ang/SYN00000_R10000\.npy: label_ang is of shape \(2, 10\), expected shape \(3, N\)"),
    row("f58-label-ang-nan", lambda r: _nan_at(r, "label_ang", (1, 0)), verdict=ERROR,
        match=r"label_ang/SYN00000_R10000\.npy: label_ang is nan at index \(1, 0\).*expected finite"),
    row("f59-label-ang-pickled", lambda r: np.save(_f(r, "DataPython", "label_ang", "N.npy"),
                                                   np.array([{"a": 1}], dtype=object), allow_pickle=True),
        verdict=ERROR, match=r"cannot read .*label_ang/SYN00000_R10000\.npy.*pickle"),
    row("f60-name-without-radius", "rename", verdict=ERROR, match=r"no rig radius for 'SYN00000'"),
    row("x-3d-gt-wrong-columns", lambda r: _npy(r, "3D_gt", np.ones((8, 2))), verdict=ERROR,
        match=r"3D_gt is of shape \(8, 2\), expected shape \(N, 3\)"),
    row("x-cam-pose-inf", lambda r: _npy(r, "cam_pose", np.array([0, np.inf, 0.0])), verdict=ERROR,
        match=r"cam_pose/SYN00000_R10000\.npy: cam_pose is inf"),
    row("x-label-ang-elevation-out-of-range", lambda r: _npy(r, "label_ang", np.array([[0, 1, 2], [0.3, 4, 0.3],
                                                                                      [-0.3, -0.3, -0.3]])),
        verdict=ERROR, match=r"label_ang/SYN00000_R10000\.npy: label_ang elevation is 4 .*expected values in \[-1\.57"),
    row("x-depth-coded-16bit", lambda r: cv2.imwrite(str(_f(r, "depth_coded", "N.png")), np.ones((H, W, 3), np.uint16)),
        verdict=ERROR, match=r"depth_coded is 64x32 3-channel uint16, expected pixel type uint8"),
    row("x-depth-coded-rgba", lambda r: cv2.imwrite(str(_f(r, "depth_coded", "N.png")), np.ones((H, W, 4), np.uint8)),
        verdict=ERROR, match=r"depth_coded is 64x32 4-channel uint8, expected a 3-channel"),
    row("x-em-rgb-refused", lambda r: cv2.imwrite(str(_f(r, "EM_gt", "N.png")), np.ones((H, W, 3), np.uint8)),
        verdict=ERROR, match=r"EM_gt is 64x32 3-channel uint8, expected a single-channel"),
    row("x-img-grayscale", lambda r: _ok_nc(r, lambda a: cv2.cvtColor(a, cv2.COLOR_BGR2GRAY)), verdict=OK),
    row("x-img-rgba", lambda r: _ok_nc(r, lambda a: np.concatenate([a, a[..., :1]], -1)), verdict=OK),
    row("x-img-16bit", lambda r: _ok_nc(r, lambda a: a.astype(np.uint16) * 257), verdict=OK),
    row("x-empty-img-folder", "empty", verdict=ERROR, match=r"no images in .*img"),
    row("x-label-cor-only-mode", _label_cor_only, verdict=OK),
    row("x-label-cor-only-without-label-folder", "no-label-folder", verdict=ERROR,
        match=r"no DataPython/label_cor/ or label_cor/ folder"),
]


def _nc_cor(fn):
    def mutate(root):
        p = _f(root, "DataPython", "label_cor", "N.txt")
        _write_cor(p, fn(np.loadtxt(p).reshape(-1, 2)))
    return mutate


def _nc_split(rows):
    rows[0, 0] += 4.0
    return rows


NONCENTRAL_ROWS += [
    row("x-label-cor-more-corners-than-3d-gt",
        _nc_cor(lambda r: np.array([[x, y] for x in np.arange(1.0, 63.0, 1.5) for y in (10.0, 22.0)])), verdict=ERROR,
        match=r"label_cor/SYN00000_R10000\.txt: label_cor is 42 corners, expected at most the \d+ corners of "
              r"SYN00000_R10000\.npy \(3D_gt"),
    row("x-label-cor-columns-differ", _nc_cor(_nc_split), verdict=ERROR,
        match=r"SYN00000_R10000\.txt: label_cor is corner 0 with ceiling x=.*in one column"),
    row("x-label-cor-duplicated", _nc_cor(lambda r: np.concatenate([r, r[:2]])), verdict=ERROR,
        match=r"SYN00000_R10000\.txt: label_cor is corner \d+ at x=.* repeating corner 0"),
    row("x-3d-gt-in-millimetres", lambda r: _npy(r, "3D_gt", np.load(_f(r, "DataPython", "3D_gt", "N.npy")) * 1000),
        verdict=ERROR, match=r"3D_gt/SYN00000_R10000\.npy: room (camera )?height is [\d.]+ m.*expected"),
    row("x-split-name-escapes", "escape", verdict=ERROR,
        match=r"train\.txt:1: path '\.\./\.\./etc/x' leaves the dataset root"),
]


@pytest.mark.parametrize("mutate, verdict, match", NONCENTRAL_ROWS)
def test_noncentral_indoor(noncentral_base, tmp_path, mutate, verdict, match):
    root = _copy(noncentral_base, tmp_path / "n")
    if mutate == "rename":
        for p in list(root.rglob(f"{NAME}.*")):
            p.rename(p.with_name(p.name.replace("_R10000", "")))
        expect(lambda: _nc(root)[0], verdict, match)
        return
    if mutate == "empty":
        _f(root, "img", "N.png").unlink()
        expect(lambda: _nc(root), verdict, match, error=FileNotFoundError)
        return
    if mutate == "escape":
        (root / "split").mkdir()
        (root / "split" / "train.txt").write_text("../../etc/x\n")
        expect(lambda: _nc(root, split="train"), verdict, match, error=CorruptSampleError)
        return
    if mutate == "no-label-folder":
        shutil.rmtree(root / "DataPython")
        expect(lambda: _nc(root, label_cor_only=True), verdict, match, error=FileNotFoundError)
        return
    if verdict == OK:
        expect(lambda: mutate(root), verdict, match)
        return
    mutate(root)
    err = expect(lambda: _nc(root)[0], verdict, match, error=CorruptSampleError)
    assert isinstance(err, CorruptSampleError)           # so training skips the sample (with a warning)


# =================================================================================================
# HoLiNet panorama folder (66-68) and whole-dataset corruption (65)
# =================================================================================================

def _rotated_folder(root):
    from omnidl.data.horizon import PanoramaFolder, RotatedPanoramas
    return RotatedPanoramas(PanoramaFolder(str(root), height=16, width=32), height=16, width=32, augment=False,
                            deterministic=True)


def _ok_black(root):
    cv2.imwrite(str(root / "b.png"), np.zeros((H, W, 3), np.uint8))
    s = _rotated_folder(root)[1]
    assert s["image"].shape == (3, 16, 32) and float(s["image"].max()) == 0.0


def _ok_gray16(root):
    cv2.imwrite(str(root / "b.png"), np.full((H, W), 65535, np.uint16))
    s = _rotated_folder(root)[1]
    assert s["image"].shape == (3, 16, 32) and float(s["image"].max()) == pytest.approx(1.0)


HORIZON_ROWS = [
    row("f66-truncated-png-skipped", lambda r: (cv2.imwrite(str(r / "b.png"), np.full((H, W, 3), 5, np.uint8)),
                                                truncate(r / "b.png")), verdict=SKIP,
        match=r"skipping sample 1: (truncated PNG|cannot decode image) .*b\.png"),
    row("f67-square-image", lambda r: cv2.imwrite(str(r / "b.png"), np.zeros((50, 50, 3), np.uint8)), verdict=SKIP,
        match=r"b\.png: panorama size is 50x50, expected an equirectangular panorama \(width = 2 x height\)"),
    row("f68-all-black", _ok_black, verdict=OK),
    row("x-gray-16bit", _ok_gray16, verdict=OK),
    row("x-zero-byte", lambda r: (r / "b.png").write_bytes(b""), verdict=SKIP, match=r"empty file .*b\.png"),
]


@pytest.mark.parametrize("mutate, verdict, match", HORIZON_ROWS)
def test_horizon_folder(tmp_path, mutate, verdict, match):
    cv2.imwrite(str(tmp_path / "a.png"), np.full((H, W, 3), 100, np.uint8))
    if verdict == OK:
        expect(lambda: mutate(tmp_path), verdict, match)
        return
    mutate(tmp_path)
    ds = SkipCorrupt(_rotated_folder(tmp_path))
    assert ds[0] is not None
    assert expect(flagged(lambda: ds[1]), verdict, match) is None


def _all_corrupt(root, n=3):
    for i in range(n):
        cv2.imwrite(str(root / f"p{i}.png"), np.zeros((H, W, 3), np.uint8))
        truncate(root / f"p{i}.png")
    from omnidl.data.folder import ImageFolder
    return ImageFolder(str(root), height=None, width=None)


def _loop_loader(ds, epochs=50):
    """What the trainer does: epochs of a DataLoader over SkipCorrupt, collating (all-None batches are None)."""
    from omnidl.data.collate import collate_samples
    loader = torch.utils.data.DataLoader(SkipCorrupt(ds), batch_size=2, collate_fn=collate_samples)
    for _ in range(epochs):
        for _batch in loader:
            pass


def _max_skips_counts_occurrences(root):
    ds = _all_corrupt(root, 1)
    cv2.imwrite(str(root / "q.png"), np.zeros((H, W, 3), np.uint8))     # one good sample after the bad one
    from omnidl.data.folder import ImageFolder
    robust = SkipCorrupt(ImageFolder(str(root), height=None, width=None), max_skips=3)
    assert len(ds) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for _ in range(3):                                                # the same bad index 3 times: fine
            assert robust[0] is None and robust[1] is not None
        robust[0]                                                         # the 4th occurrence: too many


WHOLE_ROWS = [
    row("f65-all-corrupt-training-set", lambda r: _loop_loader(_all_corrupt(r)), verdict=ERROR,
        match=r"all 3 samples read in a row were corrupt.*p2\.png"),
    row("x-one-sample-all-corrupt", lambda r: SkipCorrupt(_all_corrupt(r, 1))[0], verdict=ERROR,
        match=r"whole pass.*p0\.png"),
    row("x-max-skips-counts-every-occurrence", _max_skips_counts_occurrences, verdict=ERROR,
        match=r"4 corrupt samples skipped \(max_skips=3\) against 3 good ones; 1 distinct sample.*p0\.png"),
]


@pytest.mark.parametrize("run, verdict, match", WHOLE_ROWS)
def test_whole_dataset_corrupt(tmp_path, run, verdict, match):
    err = expect(lambda: run(tmp_path), verdict, match, error=TooManyCorruptSamples)
    assert not isinstance(err, CorruptSampleError)       # never swallowed by another SkipCorrupt


# =================================================================================================
# The validation layer itself (omnidl/data/validate.py) on odd inputs
# =================================================================================================

def _img(path, arr):
    cv2.imwrite(str(path), arr)
    return path


def _v_read_image(tmp, arr, **kw):
    from omnidl.data.validate import read_image
    return read_image(_img(tmp / "v.png", arr), "field_x", **kw)


def _v_load(tmp, arr, **kw):
    from omnidl.data.validate import load_npy
    np.save(tmp / "v.npy", arr)
    return load_npy(tmp / "v.npy", "field_y", **kw)


VALIDATE_ROWS = [
    row("x-v-gray-to-rgb", lambda t: _v_read_image(t, np.full((3, 5), 7, np.uint8)).shape == (3, 5, 3), verdict=OK),
    row("x-v-rgba-to-rgb", lambda t: _v_read_image(t, np.full((3, 5, 4), 7, np.uint8)).shape == (3, 5, 3), verdict=OK),
    row("x-v-rgb-order", lambda t: _v_read_image(t, np.array([[[1, 2, 3]]], np.uint8))[0, 0].tolist() == [3, 2, 1],
        verdict=OK),
    row("x-v-gray-refused", lambda t: _v_read_image(t, np.ones((3, 5), np.uint8), convert=False), verdict=ERROR,
        match=r"v\.png: field_x is 5x3 1-channel uint8, expected a 3-channel"),
    row("x-v-16bit-refused", lambda t: _v_read_image(t, np.ones((3, 5, 3), np.uint16), dtypes=(np.uint8,)),
        verdict=ERROR, match=r"v\.png: field_x is 5x3 3-channel uint16, expected pixel type uint8"),
    row("x-v-size", lambda t: _v_read_image(t, np.ones((3, 5, 3), np.uint8), size=(6, 3)), verdict=ERROR,
        match=r"v\.png: field_x is 5x3, expected 6x3"),
    row("x-v-1x1-image", lambda t: _v_read_image(t, np.ones((1, 1), np.uint8), channels=1).shape == (1, 1),
        verdict=OK),
    row("x-v-npy-truncated", lambda t: (np.save(t / "v.npy", np.ones((50, 3))), truncate(t / "v.npy"),
                                        __import__("omnidl.data.validate", fromlist=["x"]).load_npy(t / "v.npy", "f")),
        verdict=ERROR, match=r"cannot read .*v\.npy \(f: .*expected a complete numeric \.npy"),
    row("x-v-npy-missing", lambda t: __import__("omnidl.data.validate", fromlist=["x"]).load_npy(t / "no.npy", "f"),
        verdict=ERROR, match=r"missing file .*no\.npy"),
    row("x-v-npy-string-array", lambda t: _v_load(t, np.array(["a", "b"])), verdict=ERROR,
        match=r"v\.npy: field_y is of dtype <U1, expected a numeric array"),
    row("x-v-npy-inf", lambda t: _v_load(t, np.array([1.0, -np.inf])), verdict=ERROR,
        match=r"v\.npy: field_y is -inf at index \(1,\)"),
    row("x-v-npy-empty-ok", lambda t: _v_load(t, np.zeros((0, 3)), shape=(None, 3)).shape == (0, 3), verdict=OK),
    row("x-v-range", lambda t: __import__("omnidl.data.validate", fromlist=["x"]).check_range(
        np.array([0.5, 2.0]), "p.txt", "field_z", 0, 1), verdict=ERROR,
        match=r"p\.txt: field_z is 2 at index \(1,\).*expected values in \[0, 1\]"),
]


@pytest.mark.parametrize("run, verdict, match", VALIDATE_ROWS)
def test_validate_layer(tmp_path, run, verdict, match):
    out = expect(lambda: run(tmp_path), verdict, match, error=CorruptSampleError)
    if verdict == OK:
        assert out is True or isinstance(out, np.ndarray)


def test_corner_heat_stays_a_probability_for_any_column():
    """Defence in depth behind the label_cor checks: columns wrap on the circle, so the target stays in (0, 1]."""
    from omnidl.data.layout_targets import corner_heat
    for cols in ([1000.5], [-5.0], [63.9, 0.1], [64.0 * 7 + 3]):
        h = corner_heat(np.array(cols), 64)
        assert float(h.max()) <= 1.0 and float(h.min()) > 0
    assert torch.allclose(corner_heat(np.array([-4.5]), 64), corner_heat(np.array([59.5]), 64))
    with pytest.raises(ValueError, match="finite"):
        corner_heat(np.array([np.nan]), 64)


def test_stanford_label_list_json_kinds(tmp_path):
    """A label list that is JSON but not a list is a clear error too (kept next to rows f19/f20)."""
    write_stanford(tmp_path, areas=("1",), per_area=1, w=W, h=H)
    (tmp_path / "assets" / "semantic_labels.json").write_text(json.dumps({"a": 1}))
    with pytest.raises(ValueError, match=r"semantic_labels\.json should hold a JSON list"):
        _stanford(tmp_path)
