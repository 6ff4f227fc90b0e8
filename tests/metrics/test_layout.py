"""Layout metrics against shapely (polygon areas/intersections) and closed forms."""
import math

import numpy as np
import pytest
import torch
from shapely.geometry import Polygon

from omnidl.metrics.layout import (LayoutMetrics, binary_scores, corner_error, corner_map, edge_map, iou_2d, iou_3d,
                                   layout_scores, polygon_area, polygon_intersection_area)


def _random_star(rng, n, centre=(0.0, 0.0)):
    ang = np.sort(rng.uniform(0, 2 * math.pi, n))
    r = rng.uniform(1.0, 4.0, n)
    return np.stack([centre[0] + r * np.cos(ang), centre[1] + r * np.sin(ang)], 1)


@pytest.mark.parametrize("seed", range(6))
def test_polygon_intersection_matches_shapely(seed):
    rng = np.random.default_rng(seed)
    p = _random_star(rng, int(rng.integers(3, 12)))
    q = _random_star(rng, int(rng.integers(3, 12)), centre=rng.uniform(-2, 2, 2))
    if seed % 2:
        q = q[::-1]                                    # orientation must not matter
    ref = Polygon(p).intersection(Polygon(q)).area
    assert polygon_intersection_area(p, q) == pytest.approx(ref, rel=1e-9, abs=1e-12)
    assert abs(polygon_area(p)) == pytest.approx(Polygon(p).area)
    ref_iou = ref / Polygon(p).union(Polygon(q)).area
    assert iou_2d(p, q) == pytest.approx(ref_iou, rel=1e-9)


def test_iou_3d_closed_form_boxes():
    a = np.array([[0, 0], [2, 0], [2, 2], [0, 2]], float)
    b = a + 1.0
    # inter area 1, heights [-1, 1] vs [0, 2]: overlap 1 -> inter 1, union 8 + 8 - 1
    assert iou_3d(a, (-1, 1), b, (0, 2)) == pytest.approx(1 / 15)
    assert iou_3d(a, (-1, 1), a, (-1, 1)) == pytest.approx(1.0)


def test_corner_error_hungarian_and_unequal_counts():
    g = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    p = g[[2, 0, 1]] + np.array([0.1, 0, 0])
    assert corner_error(p, g) == pytest.approx(0.1)
    # one extra prediction 1 m from its nearest ground-truth corner
    p2 = np.concatenate([g, [[0, 0, 1.0]]])
    assert corner_error(p2, g) == pytest.approx(1.0 / 4)


def test_layout_scores_perfect_and_scaled():
    poly = np.array([[-2, -1], [3, -1], [3, 2], [-2, 2]], float)
    s = layout_scores(poly, (-1.5, 1.2), poly, (-1.5, 1.2))
    assert s["ce"] == 0 and s["iou_3d"] == pytest.approx(1.0) and s["iou_2d"] == pytest.approx(1.0)
    s2 = layout_scores(poly * 0.9, (-1.35, 1.08), poly, (-1.5, 1.2))
    assert s2["iou_3d"] < 0.80 and s2["iou_3d_u2s"] == pytest.approx(1.0)        # up-to-scale IoU ignores scale
    diag = np.linalg.norm([5, 3, 2.7])
    assert s2["cen"] == pytest.approx(s2["ce"] / diag)


def test_edge_and_corner_maps_and_scores():
    H, W = 32, 64
    bon = torch.zeros(1, 2, W)
    bon[:, 0] = -0.5
    bon[:, 1] = 0.6
    cols = [torch.tensor([10, 40])]
    e = edge_map(bon, cols, H)
    rows_c = (-0.5 / math.pi + 0.5) * H
    assert e[0, int(rows_c), 5] and e[0, H // 2, 10] and not e[0, H // 2, 5]
    c = corner_map(bon, cols, H, radius=2)
    assert c[0, int(rows_c), 10] and not c[0, int(rows_c), 20]
    s = binary_scores(e, e)
    assert s == {"precision": 1.0, "recall": 1.0, "accuracy": 1.0, "iou": 1.0}
    s2 = binary_scores(torch.zeros_like(e), e)
    assert s2["recall"] == 0 and s2["iou"] == 0


def test_layout_metrics_object_reads_hook_layouts_from_outputs():
    from omnidl.postprocess import get_hook
    from omnidl.apps.layout.simulate import Room, ring_camera, simulate_columns
    room = Room(np.array([[3.0, -2.5], [3.0, 3.5], [-2.0, 3.5], [-2.0, -2.5]]), 1.25, -1.45)
    rays, prob = simulate_columns(room, ring_camera(1.0, 256))
    lat_c, lat_f = rays.elevations()
    bon = torch.from_numpy(np.stack([-lat_c, -lat_f]))[None].float()
    logit = torch.logit(torch.from_numpy(prob).clamp(1e-4, 1 - 1e-4))[None, None].float()
    corners3d = torch.from_numpy(room.corners_3d)[None]
    m = LayoutMetrics(target_units="radians")
    batch = {"image": torch.zeros(1, 3, 128, 256), "boundary": bon, "corner": torch.from_numpy(prob)[None, None].float(),
             "corners_3d": corners3d}
    outputs = {"boundary": bon, "corner": logit}
    outputs["layout"] = get_hook("layout_manhattan")(outputs, batch, camera=ring_camera(1.0, 256))["layout"]
    m.update(outputs, batch)
    r = m.compute()
    assert r["ce"] < 0.05 and r["iou_3d"] > 0.95 and r["layout_fail_rate"] == 0
    assert r["edge_iou"] == pytest.approx(1.0) and r["boundary_px"] == pytest.approx(0.0, abs=1e-3)


def test_layout_scores_are_fractions():
    """Issue 14: CEN and the IoUs are fractions in [0, 1] like every omnidl metric (CE stays in metres)."""
    poly = np.array([[-2, -1], [3, -1], [3, 2], [-2, 2]], float)
    for pred, h in ((poly, (-1.5, 1.2)), (poly * 0.5 + 0.3, (-1.4, 1.0)), (poly * 3.0, (-2.0, 2.5))):
        s = layout_scores(pred, h, poly, (-1.5, 1.2))
        assert set(s) == {"ce", "cen", "iou_3d", "iou_3d_u2s", "iou_2d"}
        for k in ("cen", "iou_3d", "iou_3d_u2s", "iou_2d"):
            assert 0.0 <= s[k] <= 1.0, (k, s[k])
    s = layout_scores(poly * 0.5, (-1.5, 1.2), poly, (-1.5, 1.2))
    assert s["iou_2d"] == pytest.approx(0.25) and s["iou_3d"] == pytest.approx(0.25)   # a quarter of the floor area
