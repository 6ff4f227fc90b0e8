"""Robustness table: the layout pipeline on rooms that break its assumptions and on degenerate inputs.

A layout never raises on data: it returns ``ok=False`` with a reason (OK rows check both). ``ok=True`` must
mean the layout can be trusted (issue 14: the Manhattan solver said ok on an 8-corner room with oblique
walls, with 18 corners and a wrong ceiling). Programming errors (bad options, mismatched sizes) raise.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from omnidl.metrics.layout import iou_3d
from omnidl.postprocess import get_hook
from omnidl.postprocess.layout import estimate_layout, layouts_from_outputs
from omnidl.apps.layout.simulate import (Room, random_atlanta_room, random_manhattan_room, ring_camera,
                                         simulate_columns)

from .verdicts import ERROR, OK, expect, row

W = 512


def polygon_room(angles_deg, radii, h_c=1.0, h_f=-1.6) -> Room:
    a = np.radians(angles_deg)
    return Room(np.c_[radii * np.cos(a), radii * np.sin(a)], h_c, h_f)


OBLIQUE8 = polygon_room(np.array([0, 40, 95, 130, 185, 220, 280, 320]) + 17,
                        np.array([3.0, 3.4, 2.8, 3.2, 3.6, 2.9, 3.1, 3.3]))
PENTAGON = polygon_room([10, 80, 160, 230, 300], np.full(5, 3.2))
ATLANTA = random_atlanta_room(np.random.default_rng(1))
MANHATTAN = random_manhattan_room(np.random.default_rng(2))


def run(room, world, rc=1.0, **kw):
    def make():
        rays, prob = simulate_columns(room, ring_camera(rc, W), quantise=True)
        h = None if rc else -room.h_floor
        return estimate_layout(rays, prob, world=world, camera_height=kw.pop("camera_height", h), **kw)
    return make


def not_ok(pattern):
    def check(lay):
        assert not lay.ok and pattern in lay.reason, lay.reason
    return check


def assumption_fails(lay):
    assert not lay.ok and "Manhattan assumption does not hold" in lay.reason
    assert lay.info["assumptions_ok"] is False


def trusted(room, min_iou=0.9):
    def check(lay):
        assert lay.ok and lay.info["assumptions_ok"], lay.reason
        iou = iou_3d(lay.corners, (lay.h_floor, lay.h_ceiling), room.polygon, (room.h_floor, room.h_ceiling))
        assert iou > min_iou and lay.info["residual_px"] < 1.0
    return check


def corrupt(room, fn, world="atlanta", rc=1.0):
    def make():
        rays, prob = simulate_columns(room, ring_camera(rc, W), quantise=True)
        rays, prob = fn(rays, prob)
        return estimate_layout(rays, prob, world=world)
    return make


def _nan_prob(rays, prob):
    return rays, np.full_like(prob, np.nan)


def _flat_prob(rays, prob):
    return rays, np.zeros_like(prob)


def _few_valid(rays, prob):
    rays.valid[: int(0.8 * len(rays.valid))] = False
    return rays, prob


def _wrong_length(rays, prob):
    return rays, prob[:-3]


def hook(room, name, rc=1.0, **options):
    def make():
        rays, prob = simulate_columns(room, ring_camera(rc, W), quantise=True)
        lat_c, lat_f = rays.elevations()
        out = {"boundary": torch.from_numpy(np.stack([-lat_c, -lat_f]))[None].float(),
               "corner": torch.logit(torch.from_numpy(prob).clamp(1e-5, 1 - 1e-5))[None, None].float()}
        batch = {"corners_3d": torch.from_numpy(room.corners_3d)[None]}
        if rc == 0:
            batch["camera_height"] = torch.tensor([-room.h_floor])
        return get_hook(name)(out, batch, camera=ring_camera(rc, W), **options)
    return make


def fell_back(res):
    lay = res["layout"][0]
    assert res["layout_ok"] == 1.0 and lay["world"] == "atlanta" and lay["info"]["fallback_from"] == "manhattan"
    assert res["layout_iou_3d"] > 0.90        # metric scale from 512 quantised columns (Manhattan: IoU < 0.5)


ROWS = [
    row("manhattan-oblique8-noncentral-fixed", run(OBLIQUE8, "manhattan"), assumption_fails, verdict=OK),
    row("manhattan-oblique8-central-fixed", run(OBLIQUE8, "manhattan", rc=0.0), assumption_fails, verdict=OK),
    row("manhattan-pentagon-central-fixed", run(PENTAGON, "manhattan", rc=0.0), assumption_fails, verdict=OK),
    row("manhattan-pentagon-noncentral", run(PENTAGON, "manhattan"), assumption_fails, verdict=OK),
    row("manhattan-atlanta-room-fixed", run(ATLANTA, "manhattan"), assumption_fails, verdict=OK),
    row("atlanta-oblique8-noncentral", run(OBLIQUE8, "atlanta"), trusted(OBLIQUE8), verdict=OK),
    row("atlanta-oblique8-central", run(OBLIQUE8, "atlanta", rc=0.0), trusted(OBLIQUE8), verdict=OK),
    row("manhattan-manhattan-room-noncentral", run(MANHATTAN, "manhattan"), trusted(MANHATTAN), verdict=OK),
    row("manhattan-manhattan-room-central", run(MANHATTAN, "manhattan", rc=0.0), trusted(MANHATTAN), verdict=OK),
    row("hook-manhattan-falls-back-noncentral-fixed", hook(OBLIQUE8, "layout_manhattan"), fell_back, verdict=OK),
    row("hook-manhattan-falls-back-central-fixed", hook(OBLIQUE8, "layout_manhattan_central", rc=0.0), fell_back,
        verdict=OK),
    row("corner-prob-all-nan", corrupt(MANHATTAN, _nan_prob), not_ok("corner probabilities are all NaN"),
        verdict=OK),
    row("corner-prob-flat", corrupt(MANHATTAN, _flat_prob), not_ok("0 corner(s) detected"), verdict=OK),
    row("boundaries-mostly-invalid", corrupt(MANHATTAN, _few_valid), not_ok("columns have finite boundaries"),
        verdict=OK),
    row("central-rays-without-camera-height", run(MANHATTAN, "atlanta", rc=0.0, camera_height=None),
        not_ok("metric scale is unobservable"), verdict=OK),
    row("camera-height-negative", run(MANHATTAN, "atlanta", rc=0.0, camera_height=-1.0),
        not_ok("camera_height must be > 0"), verdict=OK),
    row("corner-prob-wrong-length", corrupt(MANHATTAN, _wrong_length), None, verdict=ERROR,
        match=r"corner probability has 509 columns, boundaries have 512"),
    row("unknown-world", run(MANHATTAN, "gothic"), None, verdict=ERROR,
        match=r"world must be 'manhattan' or 'atlanta', got 'gothic'"),
    row("unknown-fallback", lambda: layouts_from_outputs(
        {"boundary": torch.zeros(1, 2, 8), "corner": torch.zeros(1, 1, 8)}, {}, camera=ring_camera(1.0, 8),
        fallback="gothic"), None, verdict=ERROR, match=r"fallback must be None, 'atlanta' or 'manhattan'"),
]


@pytest.mark.parametrize("make,check,verdict,match", ROWS)
def test_layout(make, check, verdict, match):
    out = expect(make, verdict, match)
    if verdict == OK:
        check(out)


# ------------------------------------------------------------------------------------ room checks of the adapters
BOX = np.array([[-1.5, -2.0], [2.0, -2.0], [2.0, 1.5], [-1.5, 1.5]])


def _room(polygon, camera_height=1.6, ceiling_height=1.2):
    def make():
        from omnidl.data.layout_sample import check_room, check_room_units
        p = check_room(np.asarray(polygon, float), "room.json", "layout")
        check_room_units(p, camera_height, ceiling_height, "room.json")
        return p
    return make


def _setting(cls, **kw):
    def make():
        from omnidl.data import horizonnet_format, noncentral_indoor
        ds = {"hn": horizonnet_format.HorizonNetFolderDataset, "nc": noncentral_indoor.NonCentralIndoorDataset}[cls]
        return ds("/nonexistent-root", **kw)
    return make


ROOM_ROWS = [
    row("room-ok", _room(BOX), lambda p: np.array_equal(p, BOX), verdict=OK),
    row("room-duplicate-consecutive", _room(np.insert(BOX, 2, BOX[1], 0)), None, verdict=ERROR,
        match=r"room\.json: layout is corner 2 = \[2\.0, -2\.0\] repeating corner 1 \(a duplicated point\)"),
    row("room-duplicate-apart", _room(np.insert(BOX, 4, BOX[1], 0)), None, verdict=ERROR,
        match=r"corner 4 = \[2\.0, -2\.0\] repeating corner 1 \(a duplicated point\), expected each corner once"),
    row("room-bow-tie", _room(BOX[[0, 2, 1, 3]]), None, verdict=ERROR,
        match=r"room\.json: layout is a self-intersecting polygon \(4 corners\)"),
    row("room-camera-height-cm", _room(BOX, camera_height=160.0), None, verdict=ERROR,
        match=r"room\.json: room camera height is 160 m, expected 0\.3\.\.5 m above the floor"),
    row("room-camera-height-too-low", _room(BOX, camera_height=0.1), None, verdict=ERROR,
        match=r"room camera height is 0\.1 m, expected 0\.3\.\.5 m"),
    row("room-ceiling-cm", _room(BOX, ceiling_height=120.0), None, verdict=ERROR,
        match=r"room height is 121\.6 m \(floor to ceiling\), expected at most 100 m"),
    row("room-vertices-x1e4", _room(BOX * 1e4), None, verdict=ERROR,
        match=r"room polygon is 35000 m across, expected a room at most 100 m"),
    row("room-height-nan", _room(BOX, ceiling_height=float("nan")), None, verdict=ERROR,
        match=r"room ceiling height above the camera is nan, expected a finite positive height"),
    row("horizonnet-camera-height-cm", _setting("hn", camera_height=160.0), None, verdict=ERROR,
        match=r"HorizonNetFolderDataset: camera_height=160\.0; expected 0\.3\.\.5 metres"),
    row("noncentral-camera-height-nan", _setting("nc", camera_height=float("nan")), None, verdict=ERROR,
        match=r"NonCentralIndoorDataset: camera_height=nan; expected 0\.3\.\.5 metres"),
]


@pytest.mark.parametrize("make,check,verdict,match", ROOM_ROWS)
def test_room_checks(make, check, verdict, match):
    out = expect(make, verdict, match)
    if verdict == OK:
        assert check(out)
