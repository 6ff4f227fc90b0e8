"""Bad files for the benchmark adapters (PanoAnnotator JSON + split lists, ZInD, the layout sample builder) and bad
settings of the protocol metrics, one table row each, with the verdict it must get.

Each row writes a small valid dataset from the public format spec (``tests/data/adapter_fixtures.py``), breaks
one thing with ``mutate(root)``, then loads it: ERROR rows must raise an error naming the file/field/value and
what was expected, SKIP rows must leave the sample out with a warning naming it, OK rows check the value.
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from omnidl.data.pano_annotator import PanoAnnotatorLayout
from omnidl.data.robust import SkipCorrupt
from omnidl.data.zind import ZInD
from tests.data.adapter_fixtures import write_pano_annotator, write_structured3d, write_zind
from tests.robustness.verdicts import ERROR, OK, SKIP, expect, row

W, H = 64, 32
NAME = "scene0_box"            # first PanoAnnotator fixture panorama (a 4-corner room)


# ---------------------------------------------------------------------------------------------- PanoAnnotator
def _label(root: Path) -> Path:
    return root / "label" / f"{NAME}.json"


def edit_label(fn):
    def mutate(root: Path):
        p = _label(root)
        d = json.loads(p.read_text())
        fn(d)
        p.write_text(json.dumps(d))
    return mutate


def _set(*keys_value):
    *keys, value = keys_value

    def f(d):
        for k in keys[:-1]:
            d = d[k]
        d[keys[-1]] = value
    return f


def _del(*keys):
    def f(d):
        for k in keys[:-1]:
            d = d[k]
        del d[keys[-1]]
    return f


def _pts(d):
    return d["layoutPoints"]["points"]


def _walls(d):
    return d["layoutWalls"]["walls"]


def _bow(d):              # swap two corners: a self-intersecting "bow tie"
    p = _pts(d)
    p[1]["xyz"], p[2]["xyz"] = p[2]["xyz"], p[1]["xyz"]


def _outside(d):          # move the room so that the camera is outside it
    for p in _pts(d):
        p["xyz"][0] += 10.0


def _write(root: Path, rel: str, text: str | bytes):
    p = root / rel
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(text if isinstance(text, bytes) else text.encode())


def _load_pa(root: Path, split="train"):
    ds = PanoAnnotatorLayout(root, split=split, height=H, width=W)
    return [ds[i] for i in range(len(ds))]


PANO_ANNOTATOR_ROWS = [
    row("pa-not-json", lambda r: _write(r, f"label/{NAME}.json", "{not json"), verdict=ERROR,
        match=rf"{NAME}\.json.*expected JSON"),
    row("pa-binary", lambda r: _write(r, f"label/{NAME}.json", b"\xff\xfe\x00\x81"), verdict=ERROR,
        match=rf"{NAME}\.json.*not UTF-8"),
    row("pa-json-list", lambda r: _write(r, f"label/{NAME}.json", "[1, 2]"), verdict=ERROR,
        match=r"PanoAnnotator label is a JSON list, expected a JSON object"),
    row("pa-missing-cameraHeight", edit_label(_del("cameraHeight")), verdict=ERROR,
        match=rf"{NAME}\.json: cameraHeight is missing"),
    row("pa-cameraHeight-string", edit_label(_set("cameraHeight", "1.6")), verdict=ERROR,
        match=r"cameraHeight is '1\.6', expected a number"),
    row("pa-cameraHeight-nan", edit_label(_set("cameraHeight", float("nan"))), verdict=ERROR,
        match=r"cameraHeight is nan, expected a finite number"),
    row("pa-cameraHeight-negative", edit_label(_set("cameraHeight", -1.6)), verdict=ERROR,
        match=r"cameraHeight is -1\.6, expected a positive height"),
    row("pa-no-ceiling-height", edit_label(lambda d: (d.pop("cameraCeilingHeight"), d.pop("layoutHeight"))),
        verdict=ERROR, match=r"cameraCeilingHeight is missing \(and no layoutHeight\)"),
    row("pa-ceiling-below-camera", edit_label(_set("cameraCeilingHeight", -0.2)), verdict=ERROR,
        match=r"cameraCeilingHeight is -0\.2, expected a positive height"),
    row("pa-missing-layoutPoints", edit_label(_del("layoutPoints")), verdict=ERROR,
        match=r"layoutPoints is missing, expected an object \{\"num\": K, \"points\""),
    row("pa-num-mismatch", edit_label(_set("layoutPoints", "num", 7)), verdict=ERROR,
        match=r"layoutPoints\.num is 7, expected the number of points listed \(4\)"),
    row("pa-xyz-two-values", edit_label(lambda d: _pts(d)[2].update(xyz=[1.0, 2.0])), verdict=ERROR,
        match=r"layoutPoints\.points\[2\]\.xyz is \[1\.0, 2\.0\], expected a list of 3 numbers"),
    row("pa-xyz-nan", edit_label(lambda d: _pts(d)[1]["xyz"].__setitem__(0, float("nan"))), verdict=ERROR,
        match=r"points\[1\]\.xyz is nan, expected a finite number"),
    row("pa-walls-fewer", edit_label(lambda d: (_walls(d).pop(), d["layoutWalls"].update(num=3))), verdict=ERROR,
        match=r"layoutWalls is 3 walls for 4 points, expected one wall per corner"),
    row("pa-pointsIdx-out-of-range", edit_label(lambda d: _walls(d)[0].update(pointsIdx=[0, 9])), verdict=ERROR,
        match=r"walls\[0\]\.pointsIdx is \[0, 9\], expected indices in 0\.\.3"),
    row("pa-pointsIdx-float", edit_label(lambda d: _walls(d)[1].update(pointsIdx=[1.0, 2])), verdict=ERROR,
        match=r"walls\[1\]\.pointsIdx is \[1\.0, 2\], expected two integer point indices"),
    row("pa-point-used-twice", edit_label(lambda d: _walls(d)[1].update(pointsIdx=[0, 2])), verdict=ERROR,
        match=r"pointsIdx\[0\] is \[0, 0, 2, 3\], expected each point starting exactly one wall"),
    row("pa-self-intersecting", edit_label(_bow), verdict=ERROR,
        match=rf"{NAME}\.json: layoutPoints \(top view\) is a self-intersecting polygon"),
    row("pa-camera-outside", edit_label(_outside), verdict=ERROR,
        match=r"room that does not contain the camera, expected the camera \(0, 0\) inside"),
    row("pa-two-points", edit_label(lambda d: (_pts(d).__delitem__(slice(2, None)), d["layoutPoints"].update(num=2),
                                               _walls(d).__delitem__(slice(2, None)), d["layoutWalls"].update(num=2),
                                               _walls(d)[1].update(pointsIdx=[1, 0]))),
        verdict=ERROR, match=r"2 corner\(s\), expected at least 3 corners"),
    row("pa-image-not-2to1", lambda r: _write(r, f"image/{NAME}.png", _png(np.zeros((32, 32, 3), np.uint8))),
        verdict=ERROR, match=rf"{NAME}\.png: panorama is 32x32, expected an equirectangular image"),
    row("pa-image-truncated", lambda r: _write(r, f"image/{NAME}.png", (r / f"image/{NAME}.png").read_bytes()[:60]),
        verdict=ERROR, match=rf"{NAME}\.png"),
    row("pa-label-missing-for-split", lambda r: _label(r).unlink(), verdict=ERROR,
        match=rf"no label for '{NAME}'"),
    row("pa-split-unknown-name", lambda r: None, "validation", verdict=ERROR,
        match=r"unknown split 'validation'; expected one of train, val, test"),
    row("pa-split-file-missing", lambda r: (r / "split" / "val.txt").unlink(), "val", verdict=ERROR,
        match=r"no split file for split 'val' \(looked for .*val\.txt"),
    row("pa-split-three-fields", lambda r: _write(r, "split/train.txt", "a b c\n"), verdict=ERROR,
        match=r"train\.txt:1: split line is 'a b c', expected '<scene_id> <pano_id>'"),
    row("pa-split-duplicate", lambda r: _write(r, "split/train.txt", "scene0 box\nscene1 ell\nscene0 box\n"),
        verdict=ERROR, match=r"train\.txt:3: 'scene0_box' is listed twice \(first on line 1\)"),
    row("pa-split-empty", lambda r: _write(r, "split/train.txt", "# nothing\n\n"), verdict=ERROR,
        match=r"train\.txt: split list is empty"),
    row("pa-split-unknown-panorama", lambda r: _write(r, "split/train.txt", "sceneX nothere\n"), verdict=ERROR,
        match=r"split panorama 'sceneX_nothere' has no image"),
    row("pa-unlabelled-image-skipped", lambda r: _label(r).unlink(), None, verdict=SKIP,
        match=rf"left out 1 image\(s\) without a label .*{NAME}"),
    row("pa-extra-keys-ok", edit_label(lambda d: d.update(layoutObj2ds={"num": 0, "obj2ds": []}, meters=20.0)),
        verdict=OK),
    row("pa-layoutHeight-only-ok", edit_label(_del("cameraCeilingHeight")), verdict=OK),
]


def _scale_points(k):
    def f(d):
        for q in _pts(d):
            q["xyz"] = [v * k for v in q["xyz"]]
    return f


def _dup_point(d):        # corner 2 at corner 1's place: a duplicated point, not a crossing
    _pts(d)[2]["xyz"] = list(_pts(d)[1]["xyz"])


PANO_ANNOTATOR_ROWS += [
    row("pa-cameraHeight-centimetres", edit_label(_set("cameraHeight", 140.0)), verdict=ERROR,
        match=rf"{NAME}\.json: cameraHeight / layoutPoints camera height is 140 m, expected 0\.3\.\.5 m"),
    row("pa-ceiling-centimetres", edit_label(_set("cameraCeilingHeight", 120.0)), verdict=ERROR,
        match=rf"{NAME}\.json: cameraHeight / layoutPoints height is 121\.4 m .*expected at most 100 m"),
    row("pa-points-x1e4", edit_label(_scale_points(1e4)), verdict=ERROR,
        match=rf"{NAME}\.json: cameraHeight / layoutPoints polygon is 35000 m across, expected a room at most 100 m"),
    row("pa-duplicate-point", edit_label(_dup_point), verdict=ERROR,
        match=rf"{NAME}\.json: layoutPoints \(top view\) is corner 2 = .* repeating corner 1 \(a duplicated point\)"),
]


def _png(arr: np.ndarray) -> bytes:
    import cv2
    return cv2.imencode(".png", arr)[1].tobytes()


@pytest.mark.parametrize("mutate, split, verdict, match", [
    pytest.param(*(p.values if len(p.values) == 4 else (p.values[0], "train", *p.values[1:])), id=p.id, marks=p.marks)
    for p in PANO_ANNOTATOR_ROWS])
def test_pano_annotator_rows(tmp_path, mutate, split, verdict, match):
    write_pano_annotator(tmp_path, W, H)
    mutate(tmp_path)
    out = expect(lambda: _load_pa(tmp_path, split), verdict, match)
    if verdict == SKIP:
        assert len(out) == 2
    if verdict == OK:
        assert len(out) == 3 and all(s["boundary_valid"].any() for s in out)


def test_corrupt_label_is_a_flagged_skip_in_training(tmp_path):
    """Through SkipCorrupt (training) a bad label leaves the sample out with a warning naming the file."""
    import logging
    write_pano_annotator(tmp_path, W, H)
    edit_label(_bow)(tmp_path)
    ds = SkipCorrupt(PanoAnnotatorLayout(tmp_path, split="train", height=H, width=W))
    records = []
    handler = logging.Handler()
    handler.emit = records.append
    logging.getLogger("omnidl.data").addHandler(handler)
    try:
        items = [ds[i] for i in range(len(ds))]
    finally:
        logging.getLogger("omnidl.data").removeHandler(handler)
    assert sum(x is None for x in items) == 1
    assert any(f"{NAME}.json" in r.getMessage() and "self-intersecting" in r.getMessage() for r in records)


# ---------------------------------------------------------------------------------------------- ZInD
HOUSE = "0000"


def edit_zind(fn):
    def mutate(root: Path):
        p = root / HOUSE / "zind_data.json"
        d = json.loads(p.read_text())
        fn(d)
        p.write_text(json.dumps(d))
    return mutate


def _pano(d, i=1):
    return d["merger"]["floor_01"][f"complete_room_0{i}"][f"partial_room_0{i}"][f"pano_{i}"]


def _load_zind(root: Path, split="train", **kw):
    ds = ZInD(root, split=split, height=H, width=W, **kw)
    return [ds[i] for i in range(len(ds))]


ZIND_ROWS = [
    row("zind-not-json", lambda r: _write(r, f"{HOUSE}/zind_data.json", "{"), {}, verdict=ERROR,
        match=r"0000/zind_data\.json \(zind_data\.json: .*expected JSON\)"),
    row("zind-no-merger", edit_zind(lambda d: d.pop("merger")), {}, verdict=ERROR,
        match=r"zind_data\.json: merger is missing, expected a JSON object"),
    row("zind-floor-is-list", edit_zind(lambda d: d["merger"].update(floor_01=[])), {}, verdict=ERROR,
        match=r"merger\.floor_01 is a list, expected a JSON object"),
    row("zind-missing-camera_height", edit_zind(lambda d: _pano(d).pop("camera_height")), {}, verdict=ERROR,
        match=r"merger\.floor_01\.complete_room_01\.partial_room_01\.pano_1\.camera_height is missing"),
    row("zind-camera_height-string", edit_zind(lambda d: _pano(d).update(camera_height="1")), {}, verdict=ERROR,
        match=r"pano_1\.camera_height is '1', expected a finite number"),
    row("zind-ceiling-below-camera", edit_zind(lambda d: _pano(d).update(ceiling_height=0.5)), {}, verdict=ERROR,
        match=r"ceiling_height is 0\.5 with camera_height 1, expected 0 < camera_height < ceiling_height"),
    row("zind-vertices-nan", edit_zind(lambda d: _pano(d)["layout_visible"]["vertices"][0].__setitem__(0, None)), {},
        verdict=ERROR, match=r"layout_visible\.vertices is non-finite values, expected finite coordinates"),
    row("zind-vertices-triples", edit_zind(lambda d: _pano(d)["layout_visible"].update(vertices=[[0, 1, 2]] * 4)),
        {}, verdict=ERROR, match=r"layout_visible\.vertices is \[\[0, 1, 2\].*expected a list of \[x, y\] pairs"),
    row("zind-scale-string", edit_zind(lambda d: d["scale_meters_per_coordinate"].update(floor_01="big")), {},
        verdict=ERROR, match=r"scale_meters_per_coordinate\.floor_01 is 'big', expected a finite number"),
    row("zind-transformation-scale-zero",
        edit_zind(lambda d: _pano(d)["floor_plan_transformation"].update(scale=0.0)), {}, verdict=ERROR,
        match=r"floor_plan_transformation\.scale is 0\.0, expected a positive scale"),
    row("zind-image-path-empty", edit_zind(lambda d: _pano(d).update(image_path="")), {}, verdict=ERROR,
        match=r"image_path is '', expected a relative image path"),
    row("zind-image-missing", lambda r: next((r / HOUSE / "panos").iterdir()).unlink(), {}, verdict=ERROR,
        match=r"missing file .*0000/panos/.*\.jpg"),
    row("zind-house-missing", lambda r: _write(r, "zind_partition.json", json.dumps({"train": ["0042"]})), {},
        verdict=ERROR, match=r"house '0042' has no .*0042/zind_data\.json"),
    row("zind-partition-no-split", lambda r: _write(r, "zind_partition.json", json.dumps({"train": []})), "val",
        verdict=ERROR, match=r"zind_partition\.json: ZInD partition is an object with keys \['train'\], expected a 'val'"),
    row("zind-partition-not-list", lambda r: _write(r, "zind_partition.json", json.dumps({"train": "0000"})), {},
        verdict=ERROR, match=r"partition\['train'\] is a str, expected a list of house ids"),
    row("zind-unknown-split", lambda r: None, "testing", verdict=ERROR,
        match=r"unknown split 'testing'; expected one of train, val, test"),
    row("zind-unknown-layout", lambda r: None, {"layout": "merged"}, verdict=ERROR,
        match=r"layout='merged'; expected one of visible, complete, raw"),
    row("zind-self-intersecting-skipped",
        edit_zind(lambda d: _pano(d)["layout_visible"].update(vertices=[[-1, -1], [1, 1], [1, -1], [-1, 1]])), {},
        verdict=SKIP, match=r"left out 1 panorama.*0000_floor_01_pano_1 .*self-intersecting"),
    row("zind-camera-outside-skipped",
        edit_zind(lambda d: _pano(d)["layout_visible"].update(vertices=[[5, 5], [6, 5], [6, 6], [5, 6]])), {},
        verdict=SKIP, match=r"0000_floor_01_pano_1 .*does not contain the camera"),
    row("zind-outside-pano-skipped", edit_zind(lambda d: _pano(d).update(is_inside=False)), {}, verdict=SKIP,
        match=r"0000_floor_01_pano_1 \(is_inside = false\)"),
    row("zind-no-layout-skipped", edit_zind(lambda d: _pano(d).pop("layout_visible")), {}, verdict=SKIP,
        match=r"0000_floor_01_pano_1 \(no layout_visible\)"),
    row("zind-null-floor-scale-ok", edit_zind(lambda d: d["scale_meters_per_coordinate"].update(floor_01=None)), {},
        verdict=OK),
]


def _zind_vertices(fn):
    return edit_zind(lambda d: _pano(d)["layout_visible"].update(vertices=fn(_pano(d)["layout_visible"]["vertices"])))


ZIND_ROWS += [
    row("zind-image-path-dotdot", edit_zind(lambda d: _pano(d).update(image_path="../../secret.jpg")), {},
        verdict=ERROR, match=r"zind_data\.json: merger\..*pano_1\.image_path: path '\.\./\.\./secret\.jpg' leaves the "
                             r"dataset root"),
    row("zind-image-path-absolute", edit_zind(lambda d: _pano(d).update(image_path="/etc/x.jpg")), {},
        verdict=ERROR, match=r"image_path: path '/etc/x\.jpg' leaves the dataset root"),
    row("zind-transformation-scale-x1e4-skipped",
        edit_zind(lambda d: _pano(d)["floor_plan_transformation"].update(scale=2.0e4)), {}, verdict=SKIP,
        match=r"0000_floor_01_pano_1 .*camera height is 15000 m, expected 0\.3\.\.5 m"),
    row("zind-duplicate-vertex-skipped", _zind_vertices(lambda v: v[:2] + [v[1]] + v[2:]), {}, verdict=SKIP,
        match=r"0000_floor_01_pano_1 .*repeating corner 1 \(a duplicated point\)"),
]


@pytest.mark.parametrize("mutate, opts, verdict, match", ZIND_ROWS)
def test_zind_rows(tmp_path, mutate, opts, verdict, match):
    write_zind(tmp_path, W, H)
    mutate(tmp_path)
    split, kw = (opts, {}) if isinstance(opts, str) else ("train", opts)
    with warnings.catch_warnings():
        if verdict != SKIP:
            warnings.simplefilter("ignore")
        out = expect(lambda: _load_zind(tmp_path, split, **kw), verdict, match)
    if verdict == SKIP:
        assert len(out) == 5
    if verdict == OK:
        assert len(out) == 6 and out[0]["meta"]["metric"] is False


# ---------------------------------------------------------------------------------------------- protocol metrics
METRIC_ROWS = [
    row("layout-protocol-unknown", lambda: __import__("omnidl.metrics.layout_protocol", fromlist=["x"])
        .LayoutProtocolMetrics("pano"), verdict=ERROR, match=r"unknown layout protocol 'pano'; expected one of horizonnet"),
    row("depth-protocol-unknown", lambda: __import__("omnidl.metrics.depth_protocol", fromlist=["x"])
        .DepthProtocolMetrics("omni"), verdict=ERROR, match=r"unknown depth protocol 'omni'; expected one of fredsnet"),
    row("depth-protocol-bad-cap", lambda: __import__("omnidl.metrics.depth_protocol", fromlist=["x"])
        .get_depth_protocol("fredsnet", cap="cut"), verdict=ERROR, match=r"cap='cut'; expected 'mask' or 'clamp'"),
    row("layout-floor-above-camera", lambda: __import__("omnidl.metrics.layout_protocol", fromlist=["x"])
        .protocol_scores(np.eye(3)[:, :2] - 0.3, (0.5, 1.0), np.eye(3)[:, :2] - 0.3, (-1.6, 1.0)), verdict=ERROR,
        match=r"floor height 0\.5 must be below the camera"),
]


@pytest.mark.parametrize("fn, verdict, match", METRIC_ROWS)
def test_metric_rows(fn, verdict, match):
    expect(fn, verdict, match)


# ---------------------------------------------------------------------------------------------- EXR / Pano3D
def _pano3d(mutate):
    def make(root: Path):
        from tests.data.test_pano3d import write_views
        write_views(root)
        mutate(root)
        from omnidl.data.pano3d import Pano3D
        return lambda: [s for s in Pano3D(root, split_file=root / "test.txt", height=None, width=None)]
    return make


def _exr(root: Path) -> Path:
    return root / "M3D" / "v0_depth_0_Left_Down_0.0.exr"


def _rewrite_exr(planes, compression=0):
    def mutate(root: Path):
        from tests.data.test_pano3d import write_exr
        write_exr(_exr(root), planes, compression)
    return mutate


def _patch_bytes(offset, data):
    def mutate(root: Path):
        b = bytearray(_exr(root).read_bytes())
        b[offset:offset + len(data)] = data
        _exr(root).write_bytes(bytes(b))
    return mutate


def _set_compression(code):
    def mutate(root: Path):
        b = bytearray(_exr(root).read_bytes())
        i = b.find(b"compression\0compression\0") + len(b"compression\0compression\0") + 4
        b[i] = code
        _exr(root).write_bytes(bytes(b))
    return mutate


def _exr_depth_nan(root: Path):
    from omnidl.data.exr import read_exr_depth
    from tests.data.test_pano3d import write_exr
    d = np.ones((4, 8), np.float32)
    d[1, 2] = np.nan
    write_exr(root / "n.exr", {"Y": d})
    return lambda: read_exr_depth(root / "n.exr")


DEPTH_ROWS = [
    row("exr-not-exr", _pano3d(lambda r: _exr(r).write_bytes(b"\x89PNG\r\n\x1a\n" + b"0" * 40)), verdict=ERROR,
        match=r"v0_depth_0_Left_Down_0\.0\.exr is not an OpenEXR file"),
    row("exr-truncated", _pano3d(lambda r: _exr(r).write_bytes(_exr(r).read_bytes()[:-40])), verdict=ERROR,
        match=r"(truncated|corrupt) EXR file .*v0_depth"),
    row("exr-tiled-flag-without-tiles", _pano3d(_patch_bytes(4, bytes([2, 2, 0, 0]))), verdict=ERROR,
        match=r"corrupt EXR file .*v0_depth_0_Left_Down_0\.0\.exr \(OpenEXR"),
    row("exr-piz-flag-on-zips-data", _pano3d(_set_compression(4)), verdict=ERROR,
        match=r"corrupt EXR file .*v0_depth_0_Left_Down_0\.0\.exr"),
    row("exr-two-unnamed-channels", _pano3d(_rewrite_exr({"A": np.ones((16, 32), np.float32),
                                                          "B": np.ones((16, 32), np.float32)})), verdict=ERROR,
        match=r"EXR channels is \['A', 'B'\], expected a single depth channel"),
    row("exr-wrong-size", _pano3d(_rewrite_exr({"Y": np.ones((8, 16), np.float32)})), verdict=ERROR,
        match=r"v0_depth_0_Left_Down_0\.0\.exr: EXR depth is 16x8, expected 32x16"),
    row("exr-depth-nan-strict", _exr_depth_nan, verdict=ERROR,
        match=r"n\.exr: EXR depth channel 'Y' is nan at pixel \(row 1, col 2\)"),
    row("pano3d-nan-is-invalid-ok", _pano3d(_rewrite_exr({"Y": np.where(np.eye(16, 32) > 0, np.nan, 2.0)
                                                          .astype(np.float32)})), verdict=OK),
    row("pano3d-list-three-fields", _pano3d(lambda r: (r / "test.txt").write_text("a b c\n")), verdict=ERROR,
        match=r"test\.txt:1: split line is 'a b c', expected '<rgb path> <depth path>'"),
    row("pano3d-depth-missing", _pano3d(lambda r: _exr(r).unlink()), verdict=ERROR,
        match=r"missing file .*v0_depth_0_Left_Down_0\.0\.exr \(of view v0_color"),
]


def _openexr_rewrite(compression: str, tiled: bool = False):
    """The nan-is-invalid view rewritten by the OpenEXR package with another compression (PIZ, tiled ...)."""
    def mutate(root: Path):
        import OpenEXR
        header = {"compression": getattr(OpenEXR, f"{compression}_COMPRESSION"), "type": OpenEXR.scanlineimage}
        if tiled:
            tiles = OpenEXR.TileDescription()
            tiles.xSize = tiles.ySize = 8
            header.update(type=OpenEXR.tiledimage, tiles=tiles)
        y = np.where(np.eye(16, 32) > 0, np.nan, 2.0).astype(np.float32)
        OpenEXR.File(header, {"Y": y}).write(str(_exr(root)))
    return mutate


DEPTH_ROWS += [
    row("exr-piz-ok", _pano3d(_openexr_rewrite("PIZ")), verdict=OK),
    row("exr-piz-tiled-ok", _pano3d(_openexr_rewrite("PIZ", tiled=True)), verdict=OK),
    row("exr-zip-ok", _pano3d(_openexr_rewrite("ZIP")), verdict=OK),
    row("pano3d-depth-millimetres", _pano3d(_rewrite_exr({"Y": np.full((16, 32), 2500.0, np.float32)})), verdict=ERROR,
        match=r"v0_depth_0_Left_Down_0\.0\.exr: EXR depth channel 'Y' is of median 2500 m .*wrong unit"),
    row("pano3d-list-dotdot", _pano3d(lambda r: (r / "test.txt").write_text("../x_color.png ../x_depth.exr\n")),
        verdict=ERROR, match=r"test\.txt:1: path '\.\./x_color\.png' leaves the dataset root"),
    row("pano3d-list-absolute", _pano3d(lambda r: (r / "test.txt").write_text("M3D/a.png /tmp/x_depth.exr\n")),
        verdict=ERROR, match=r"test\.txt:1: path '/tmp/x_depth\.exr' leaves the dataset root"),
]


# ---------------------------------------------------------------------------------------------- Structured3D
S3D_PANO = "scene_00000/2D_rendering/485142/panorama"


def _s3d(mutate, **kw):
    def make(root: Path):
        from tests.data.adapter_fixtures import write_structured3d
        write_structured3d(root)
        mutate(root)
        from omnidl.data.structured3d import Structured3D
        return lambda: [s for s in Structured3D(root, split="train", height=None, width=None, **kw)]
    return make


def _imwrite(rel, arr):
    def mutate(root: Path):
        import cv2
        cv2.imwrite(str(root / rel), arr)
    return mutate


STRUCTURED3D_ROWS = [
    row("s3d-semantic-id-41", _s3d(_imwrite(f"{S3D_PANO}/full/semantic.png", np.full((32, 64), 45, np.uint8))),
        verdict=ERROR, match=r"semantic\.png: semantic is label id\(s\) \[45\], expected NYUv2-40 ids 0\.\.40"),
    row("s3d-semantic-rgb", _s3d(_imwrite(f"{S3D_PANO}/full/semantic.png", np.zeros((32, 64, 3), np.uint8))),
        verdict=ERROR,
        match=r"semantic\.png: semantic is 64x32 3-channel uint8, expected a single-channel \(or palette\)"),
    row("s3d-depth-wrong-size", _s3d(_imwrite(f"{S3D_PANO}/full/depth.png", np.ones((16, 32), np.uint16))),
        verdict=ERROR, match=r"depth\.png.*32x16.*64x32"),
    row("s3d-depth-missing", _s3d(lambda r: (r / S3D_PANO / "full" / "depth.png").unlink()), verdict=ERROR,
        match=r"rgb_rawlight\.png has no depth\.png"),
    row("s3d-layout-odd", _s3d(lambda r: (r / S3D_PANO / "layout.txt").write_text("1 2\n3 4\n5 6\n"), layout=True),
        verdict=ERROR, match=r"layout\.txt: .*3 points.*ceiling/floor pairs"),
    row("s3d-layout-out-of-image", _s3d(lambda r: (r / S3D_PANO / "layout.txt").write_text(
        "10 5\n10 25\n30 5\n30 25\n99 5\n99 25\n"), layout=True), verdict=ERROR,
        match=r"layout\.txt: label_cor x is 99 at index \(4,\).*expected values in"),
    row("s3d-unknown-scene", lambda r: (lambda: __import__("omnidl.data.structured3d", fromlist=["x"])
                                        .Structured3D(r, scenes=["scene_99999"])), verdict=ERROR,
        match=r"scene 'scene_99999' has no .*scene_99999/2D_rendering"),
]


def _s3d_layout(fn):
    """Rewrite ``layout.txt`` (the fixture's 4-corner box, ceiling/floor pairs) with ``fn(rows)``."""
    def mutate(root: Path):
        p = root / S3D_PANO / "layout.txt"
        rows = np.loadtxt(p).reshape(-1, 2)
        p.write_text("".join(f"{x:.3f} {y:.3f}\n" for x, y in fn(rows.copy())))
    return mutate


def _s3d_palette_ok(root: Path):
    from PIL import Image
    from omnidl.data.structured3d import Structured3D, nyu40_lut
    write_structured3d(root)
    p = root / S3D_PANO / "full" / "semantic.png"
    ids = np.asarray(Image.open(p))
    im = Image.fromarray(ids).convert("P")
    im.putpalette(list(range(256)) * 3)
    im.putdata(ids.reshape(-1).tolist())
    im.save(p)

    def check():
        s = Structured3D(root, split="train", height=None, width=None)[0]
        assert np.array_equal(s["semantic"].numpy(), nyu40_lut()[ids])
        return True
    return check


def _split_column(rows):
    rows[2, 0] += 5.0                       # the ceiling point of corner 1 five columns off its floor point
    return rows


STRUCTURED3D_ROWS += [
    row("s3d-semantic-palette-ok", _s3d_palette_ok, verdict=OK),
    row("s3d-layout-corner-duplicated", _s3d(_s3d_layout(lambda r: np.concatenate([r, r[:2]])), layout=True),
        verdict=ERROR, match=r"layout\.txt: label_cor is corner 4 at x=.* repeating corner 0, expected each corner"),
    row("s3d-layout-corners-out-of-order", _s3d(_s3d_layout(lambda r: r[[0, 1, 4, 5, 2, 3, 6, 7]]), layout=True),
        verdict=ERROR, match=r"layout\.txt: label_cor \(top view of the floor corners\) is a self-intersecting"),
    row("s3d-layout-ceiling-floor-columns-differ", _s3d(_s3d_layout(_split_column), layout=True), verdict=ERROR,
        match=r"layout\.txt: label_cor is corner 1 with ceiling x=.* and floor x=.*expected the ceiling and floor "
              r"point of a corner in one column \(within W/100 = 0\.64 px\)"),
    row("s3d-depth-metres-read-as-mm", _s3d(_imwrite(f"{S3D_PANO}/full/depth.png", np.full((32, 64), 3, np.uint16))),
        verdict=ERROR, match=r"depth\.png: depth map is of median 0\.003 m .*wrong unit"),
]


# ---------------------------------------------------------------------------------------------- skybox
def _skybox(mutate):
    def make(root: Path):
        import cv2
        d = root / "scA" / "matterport_skybox_images"
        d.mkdir(parents=True)
        for k in range(6):
            cv2.imwrite(str(d / f"p1_skybox{k}_sami.jpg"), np.full((16, 16, 3), 30 * k, np.uint8))
        mutate(d)
        from omnidl.data.skybox import Matterport3DSkybox
        return lambda: [s for s in Matterport3DSkybox(root, height=8, width=16)]
    return make


def _face(k, arr):
    def mutate(d: Path):
        import cv2
        cv2.imwrite(str(d / f"p1_skybox{k}_sami.jpg"), arr)
    return mutate


SKYBOX_ROWS = [
    row("skybox-face-missing", _skybox(lambda d: (d / "p1_skybox3_sami.jpg").unlink()), verdict=ERROR,
        match=r"skybox p1: missing \[.*p1_skybox3_sami\.jpg'\]"),
    row("skybox-face-not-square", _skybox(_face(2, np.zeros((16, 24, 3), np.uint8))), verdict=ERROR,
        match=r"p1_skybox2_sami\.jpg: skybox face is 24x16, expected a square image"),
    row("skybox-face-size-differs", _skybox(_face(4, np.zeros((8, 8, 3), np.uint8))), verdict=ERROR,
        match=r"p1_skybox4_sami\.jpg: skybox face is 8x8, expected 16x16 \(the size of face 0\)"),
    row("skybox-face-corrupt", _skybox(lambda d: (d / "p1_skybox5_sami.jpg").write_bytes(b"\xff\xd8\xff garbage")),
        verdict=ERROR, match=r"cannot decode image .*p1_skybox5_sami\.jpg"),
]


@pytest.mark.parametrize("make, verdict, match", DEPTH_ROWS + STRUCTURED3D_ROWS + SKYBOX_ROWS)
def test_depth_and_panorama_rows(tmp_path, make, verdict, match):
    out = expect(make(tmp_path), verdict, match)
    if verdict == OK and out is not True:                # rows returning True checked their value themselves
        assert out[0]["meta"]["invalid_depth"] == 16 and float(out[0]["depth"].max()) == 2.0
