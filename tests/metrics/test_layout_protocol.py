import math

import numpy as np
import pytest
from omegaconf import OmegaConf

from omnidl.metrics.layout_protocol import (LAYOUT_PROTOCOLS, LayoutProtocolMetrics, at_camera_height, corner_group,
                                            corner_pixels, layout_surfaces, protocol_scores)

BOX = np.array([[-2.0, -2.0], [2.0, -2.0], [2.0, 2.0], [-2.0, 2.0]])
ELL = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 2.0], [2.0, 2.0], [2.0, 4.0], [0.0, 4.0]]) - 1.0
TRI = np.array([[-2.0, -1.0], [2.0, -1.0], [0.0, 3.0]])
SLANT = np.array([[-1.8, -1.2], [1.6, -2.0], [2.4, 1.0], [0.2, 2.2], [-1.6, 1.4]])


# ---------------------------------------------------------------------------------------------- hand-computed IoU
@pytest.mark.parametrize("pred, ph, gt, gh, iou2, iou3", [
    # convex: overlap [-1,2]x[-2,2] = 12 of two 16 m² rooms; heights 2.6 / 3.0 m
    (BOX + [1.0, 0.0], (-1.6, 1.0), BOX, (-1.6, 1.4), 12 / 20, 12 * 2.6 / (16 * 3.0 + 16 * 2.6 - 12 * 2.6)),
    # L-shape (12 m²) inside its 4x4 bounding square (16 m²); heights 3.0 / 2.8 m
    (np.array([[-1.0, -1.0], [3.0, -1.0], [3.0, 3.0], [-1.0, 3.0]]), (-1.6, 1.4), ELL, (-1.6, 1.2), 12 / 16,
     12 * 2.8 / (12 * 2.8 + 16 * 3.0 - 12 * 2.8)),
    # non-Manhattan: the 2x2 square touching the inside of a triangle of area 8; equal heights
    (np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]), (-1.6, 1.2), TRI, (-1.6, 1.2), 4 / 8, 4 / 8),
])
def test_iou_hand_computed(pred, ph, gt, gh, iou2, iou3):
    for name in LAYOUT_PROTOCOLS:
        s = protocol_scores(pred, ph, gt, gh, name)
        assert s["iou_2d"] == pytest.approx(iou2, abs=1e-8)
        assert s["iou_3d"] == pytest.approx(iou3, abs=1e-8)


def test_fixed_camera_height_rescales_both_rooms():
    # the prediction at half scale with its floor at -0.8 m is the same room at camera height 1.6 m
    s = protocol_scores((BOX + [1.0, 0.0]) / 2, (-0.8, 0.5), BOX, (-1.6, 1.4), "horizonnet")
    assert s["iou_2d"] == pytest.approx(0.60, abs=1e-8)
    assert s["iou_3d"] == pytest.approx(31.2 / 58.4, abs=1e-8)
    # without rescaling (metric protocol) the half-size room overlaps much less
    assert protocol_scores((BOX + [1.0, 0.0]) / 2, (-0.8, 0.5), BOX, (-1.6, 1.4), "metric")["iou_2d"] < 0.30
    p, h = at_camera_height(BOX, (-3.2, 2.0), 1.6)
    assert np.allclose(p, BOX / 2) and h == (-1.6, 1.0)


@pytest.mark.parametrize("room", [BOX, ELL, TRI, SLANT])
def test_iou_matches_shapely(room):
    shapely = pytest.importorskip("shapely.geometry")
    rng = np.random.default_rng(0)
    for _ in range(5):
        pred = room @ np.array([[1.1, 0.05], [-0.05, 0.9]]) + rng.normal(0, 0.2, 2)
        s = protocol_scores(pred, (-1.6, 1.1), room, (-1.6, 1.3), "horizonnet")
        P, Q = shapely.Polygon(pred), shapely.Polygon(room)
        inter = P.intersection(Q).area
        assert s["iou_2d"] == pytest.approx(inter / (P.area + Q.area - inter), abs=1e-8)
        v = inter * 2.7
        assert s["iou_3d"] == pytest.approx(v / (P.area * 2.7 + Q.area * 2.9 - v), abs=1e-8)


@pytest.mark.parametrize("room", [BOX, ELL, TRI, SLANT])
@pytest.mark.parametrize("name", list(LAYOUT_PROTOCOLS))
def test_perfect_prediction(room, name):
    s = protocol_scores(room, (-1.5, 1.2), room, (-1.5, 1.2), name)
    assert s["iou_2d"] == pytest.approx(1.0, abs=1e-11) and s["iou_3d"] == pytest.approx(1.0, abs=1e-11)
    assert s["depth_rmse"] == 0.0 and s["depth_delta1"] == 1.0
    if len(room) == 4:
        assert s["corner_error"] == 0.0 and s["pixel_error"] == 0.0


# ---------------------------------------------------------------------------------------------- layout depth / CE / PE
def _brute_force(poly, h_f, h_c, W, H):
    """Range to the first surface by intersecting every pixel ray with both planes and every wall segment."""
    depth, lab = np.zeros((H, W)), np.zeros((H, W), int)
    for i in range(H):
        lat = math.pi / 2 - math.pi * (i + 0.5) / H
        for j in range(W):
            lon = 2 * math.pi * (j + 0.5) / W - math.pi
            d = np.array([math.cos(lat) * math.sin(lon), math.cos(lat) * math.cos(lon), math.sin(lat)])
            best, kind = np.inf, -1
            for k in range(len(poly)):
                a, b = poly[k], poly[(k + 1) % len(poly)]
                M = np.array([[d[0], a[0] - b[0]], [d[1], a[1] - b[1]]])
                if abs(np.linalg.det(M)) < 1e-12:
                    continue
                t, s = np.linalg.solve(M, a)
                if t > 0 and 0 <= s <= 1 and h_f <= t * d[2] <= h_c and t < best:
                    best, kind = t, 1
            for h, kd in ((h_c, 0), (h_f, 2)):
                if d[2] * h > 0 and h / d[2] < best:
                    best, kind = h / d[2], kd
            depth[i, j], lab[i, j] = best, kind
    return depth, lab


@pytest.mark.parametrize("room", [BOX, ELL, SLANT])
def test_layout_depth_against_brute_force(room):
    d, lab = layout_surfaces(room, (-1.6, 1.2), 32, 16)
    d0, lab0 = _brute_force(room, -1.6, 1.2, 32, 16)
    assert np.allclose(d, d0, rtol=1e-9) and (lab == lab0).all()


def test_cuboid_corner_error_hand_computed():
    W, H = 1024, 512
    gt, pred = BOX, BOX * 1.25                       # same corner columns, rows differ
    c = corner_pixels(gt, (-1.6, 1.2), W, H)
    assert np.allclose(np.sort(c[:, 0, 0]), [W / 8, 3 * W / 8, 5 * W / 8, 7 * W / 8])
    r, r2 = 2 * math.sqrt(2), 2.5 * math.sqrt(2)
    dv = [(math.atan(1.2 / r) - math.atan(1.2 / r2)) / math.pi * H, (math.atan(1.6 / r) - math.atan(1.6 / r2)) / math.pi * H]
    ce = (dv[0] + dv[1]) / 2 / math.hypot(W, H)
    s = protocol_scores(pred, (-1.6, 1.2), gt, (-1.6, 1.2), "metric")
    assert s["corner_error"] == pytest.approx(ce, abs=1e-8)
    _, la = _brute_force(gt, -1.6, 1.2, 64, 32)
    _, lb = _brute_force(pred, -1.6, 1.2, 64, 32)
    from omnidl.metrics.layout_protocol import cuboid_errors
    pe = cuboid_errors((pred, (-1.6, 1.2)), (gt, (-1.6, 1.2)), 64, 32)["pixel_error"]
    assert pe == pytest.approx((la != lb).mean(), abs=1e-11) and pe > 0


def test_corner_error_ignores_polygon_orientation():
    s = protocol_scores(BOX[::-1], (-1.6, 1.2), np.roll(BOX, 1, 0), (-1.6, 1.2), "lgtnet")
    assert s["corner_error"] == 0.0 and s["pixel_error"] == 0.0


def test_layout_depth_rmse_hand_computed():
    # a room scaled by k about the camera with the same heights: walls move, so only wall pixels change
    s = protocol_scores(BOX, (-1.6, 1.2), BOX, (-1.6, 1.2), "lgtnet")
    assert s["depth_rmse"] == 0
    d1, _ = layout_surfaces(BOX * 1.1, (-1.6, 1.2), 256, 128)
    d0, _ = layout_surfaces(BOX, (-1.6, 1.2), 256, 128)
    s = protocol_scores(BOX * 1.1, (-1.6, 1.2), BOX, (-1.6, 1.2), "lgtnet")
    assert s["depth_rmse"] == pytest.approx(float(np.sqrt(np.mean((d1 - d0) ** 2))), abs=1e-12)
    assert s["depth_delta1"] == 1.0


# ---------------------------------------------------------------------------------------------- the engine metric
def _batch(rooms):
    import torch
    from omnidl.data.layout_sample import room_to_corners_cam
    cc = torch.zeros(len(rooms), 8, 2, 3, dtype=torch.float64)
    for b, (p, h) in enumerate(rooms):
        cc[b, : len(p)] = torch.from_numpy(room_to_corners_cam(p, -h[0], h[1]))
    return {"corners_cam": cc, "num_walls": torch.tensor([len(p) for p, _ in rooms])}


def test_metric_object_averages_groups_and_failures():
    m = LayoutProtocolMetrics("horizonnet", maps=False)
    batch = _batch([(BOX, (-1.6, 1.4)), (ELL, (-1.6, 1.2)), (TRI, (-1.6, 1.2))])
    layouts = [{"ok": True, "corners_2d": (BOX + [1.0, 0]).tolist(), "h_floor": -1.6, "h_ceiling": 1.0},
               {"ok": False}, {"ok": True, "corners_2d": TRI.tolist(), "h_floor": -1.6, "h_ceiling": 1.2}]
    m.update({"layout": layouts}, batch)
    out = m.compute()
    assert out["iou_2d"] == pytest.approx((0.60 + 0.0 + 1.0) / 3, abs=1e-8)
    assert out["layout_fail_rate"] == pytest.approx(1 / 3) and out["gt_skipped"] == 0.0
    assert out["iou_2d@4"] == pytest.approx(0.60, abs=1e-8) and out["iou_2d@6"] == 0.0
    assert out["iou_2d@odd"] == pytest.approx(1.0)
    m.reset()
    assert m.compute() == {}


def test_invalid_ground_truth_is_skipped():
    m = LayoutProtocolMetrics("lgtnet", maps=False)
    bow = np.array([[-1.0, -1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, 1.0]])       # self-intersecting
    assert m.add((BOX, (-1.6, 1.2)), (bow, (-1.6, 1.2))) == {}
    assert m.compute() == {"gt_skipped": 1.0}


def test_unknown_protocol_and_group_names():
    with pytest.raises(ValueError, match="unknown layout protocol 'zillow'.*horizonnet"):
        LayoutProtocolMetrics("zillow")
    assert [corner_group(n) for n in (4, 6, 8, 10, 14, 5)] == ["4", "6", "8", "10+", "10+", "odd"]


@pytest.mark.parametrize("name", list(LAYOUT_PROTOCOLS))
def test_config_selects_protocol_by_name(name):
    from pathlib import Path
    from hydra.utils import instantiate
    cfg = OmegaConf.load(Path(__file__).resolve().parents[2] / "configs" / "metrics" / "layout_protocol.yaml")
    cfg.protocol = name
    m = instantiate(cfg)
    assert m.protocol.name == name and m.maps is not None


def test_degenerate_predictions():
    bow = np.array([[-1.0, -1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, 1.0]])
    assert protocol_scores(bow, (-1.6, 1.2), BOX, (-1.6, 1.2)) == {"iou_2d": 0.0, "iou_3d": 0.0}
    assert protocol_scores(BOX[:2], (-1.6, 1.2), BOX, (-1.6, 1.2)) == {"iou_2d": 0.0, "iou_3d": 0.0}
    away = protocol_scores(BOX + [5.0, 0.0], (-1.6, 1.2), BOX, (-1.6, 1.2))   # camera outside the prediction
    assert set(away) == {"iou_2d", "iou_3d"} and away["iou_2d"] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("room, hook", [("box", "layout_manhattan_central"), ("ell", "layout_manhattan_central"),
                                        ("slant", "layout_atlanta_central")])
def test_ground_truth_targets_through_the_hook_score_near_100(tmp_path, room, hook):
    """Dataset sample -> its own boundary/corner targets as network outputs -> central layout hook -> protocol
    metrics: the conventions of adapter, hook and metric agree (camera height from the batch)."""
    import sys
    from pathlib import Path
    import torch
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "data"))
    from adapter_fixtures import ROOMS, write_pano_annotator
    from omnidl.cameras import Equirectangular
    from omnidl.data.collate import collate_samples
    from omnidl.data.pano_annotator import PanoAnnotatorLayout
    from omnidl.geometry.boundary import rows_to_angles
    from omnidl.postprocess.registry import get_hook
    write_pano_annotator(tmp_path, 512, 256, rooms={room: ROOMS[room]}, splits={})
    batch = collate_samples([PanoAnnotatorLayout(tmp_path, split=None, height=256, width=512)[0]])
    heat = batch["corner_heat"].clamp(1e-4, 1 - 1e-4)
    outputs = {"boundary": rows_to_angles(batch["boundary"], 256), "corner": torch.log(heat / (1 - heat))}
    outputs.update(get_hook(hook)(outputs, batch, camera=Equirectangular(width=512, height=256)))
    m = LayoutProtocolMetrics("horizonnet", maps=False)
    m.update(outputs, batch)
    out = m.compute()
    assert out["layout_fail_rate"] == 0.0 and out["iou_2d"] > 0.999 and out["iou_3d"] > 0.999
    assert out["depth_rmse"] < 1e-3 and out.get("corner_error", 0.0) < 1e-4 and out.get("pixel_error", 0.0) < 1e-4


@pytest.mark.parametrize("name", list(LAYOUT_PROTOCOLS))
def test_scores_are_fractions(name):
    """Issue 14: IoUs, corner and pixel error are fractions in [0, 1] (depth_rmse in metres); a cuboid
    half a metre off scores a corner error well below 1 (it was in percent before)."""
    s = protocol_scores(BOX + [0.5, 0.0], (-1.6, 1.2), BOX, (-1.6, 1.2), name)
    assert {"iou_2d", "iou_3d", "corner_error", "pixel_error", "depth_delta1", "depth_rmse"} <= set(s)
    for k in ("iou_2d", "iou_3d", "corner_error", "pixel_error", "depth_delta1"):
        assert 0.0 <= s[k] <= 1.0, (k, s[k])
    assert 0.0 < s["corner_error"] < 0.1 and 0.0 < s["pixel_error"] < 0.5 and 0.5 < s["iou_2d"] < 1.0
