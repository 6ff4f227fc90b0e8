"""Room sampling: Table A.2 limits (checked with shapely as the oracle), Atlanta share, determinism."""
import math

import numpy as np
import pytest
from shapely.geometry import Polygon

from omnidl.synth import RoomLimits, check_room, is_manhattan, sample_floor_plan, sample_room
from omnidl.synth.room import sample_manhattan_polygon

N_ROOMS = 300


def _angles(poly):
    e = np.roll(poly, -1, 0) - poly
    out = []
    for k in range(len(poly)):
        a, b = e[k - 1], e[k]
        out.append(math.degrees(math.acos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))
    return np.array(out)


@pytest.fixture(scope="module")
def rooms():
    return [sample_room(seed, furniture=False) for seed in range(N_ROOMS)]


def test_every_room_satisfies_table_a2(rooms):
    lim = RoomLimits()
    for sc in rooms:
        poly = sc.polygon
        shp = Polygon(poly)
        assert shp.is_valid and shp.exterior.is_ccw
        assert 25.0 <= shp.area <= 110.0
        assert 4 <= len(poly) <= 14
        lengths = np.linalg.norm(np.roll(poly, -1, 0) - poly, axis=1)
        assert lengths.min() >= 0.5 - 1e-9 and lengths.max() <= 8.0 + 1e-9
        ang = _angles(poly)
        assert ang.min() >= 25.0 - 1e-6 and ang.max() <= 100.0 + 1e-6
        assert 2.5 <= sc.height <= 4.25
        assert check_room(poly, sc.height, lim) == []


def test_atlanta_share_at_default_ratio(rooms):
    atlanta = np.mean([not sc.manhattan for sc in rooms])
    assert atlanta >= 0.30
    # Atlanta rooms really have oblique walls, Manhattan ones only axis-aligned walls
    for sc in rooms[:50]:
        e = np.roll(sc.polygon, -1, 0) - sc.polygon
        axis = (np.abs(e[:, 0]) < 1e-9) | (np.abs(e[:, 1]) < 1e-9)
        assert axis.all() == sc.manhattan


def test_ratio_one_gives_manhattan_rooms():
    for seed in range(30):
        assert is_manhattan(sample_floor_plan(np.random.default_rng(seed), manhattan_ratio=1.0))


def test_manhattan_plans_are_rectilinear_and_valid():
    for seed in range(30):
        p = sample_manhattan_polygon(np.random.default_rng(seed))
        assert is_manhattan(p) and Polygon(p).is_valid


def test_check_room_reports_violations():
    square = np.array([[0, 0], [9.0, 0], [9, 9], [0, 9]])
    bad = check_room(square, 5.0)
    assert any("wall lengths" in b for b in bad) and any("height" in b for b in bad)
    assert check_room(np.array([[0, 0], [6.0, 0], [6, 6], [0, 6]]), 3.0) == []
    tri_ish = np.array([[0, 0], [8.0, 0], [0.3, 6]])
    assert any("walls" in b for b in check_room(tri_ish, 3.0))


def test_same_seed_same_scene():
    a, b = sample_room(123), sample_room(123)
    for f in ("polygon", "boxes", "decals", "lights", "box_material", "wall_material"):
        assert np.array_equal(getattr(a, f), getattr(b, f))
    assert a.height == b.height
    assert not np.array_equal(sample_room(124).polygon, a.polygon) or sample_room(124).height != a.height


def test_furniture_inside_room_and_not_overlapping():
    from shapely.geometry import Polygon as P
    for seed in range(15):
        sc = sample_room(seed)
        room = P(sc.polygon).buffer(1e-6)
        fps = [P(f) for f in sc.footprints]
        for i, f in enumerate(fps):
            assert room.contains(f)
            for g in fps[i + 1:]:
                assert f.intersection(g).area < 1e-9
        # boxes lie between floor and ceiling
        if len(sc.boxes):
            assert (sc.boxes[:, 2] - sc.boxes[:, 5]).min() >= -1e-9
            assert (sc.boxes[:, 2] + sc.boxes[:, 5]).max() <= sc.height + 1e-9
