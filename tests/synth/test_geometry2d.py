"""2D polygon helpers against shapely."""
import numpy as np
from shapely.geometry import Point, Polygon

from omnidl.synth.geometry2d import (distance_to_edges, is_simple, points_in_polygon, polygon_area, polygon_inside,
                                     polygons_overlap, rect_corners, remove_collinear, turn_angles_deg)

L_SHAPE = np.array([[0, 0], [4.0, 0], [4, 2], [2, 2], [2, 5], [0, 5]])


def test_area_inside_distance_match_shapely():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 6, size=(400, 2))
    shp = Polygon(L_SHAPE)
    assert np.isclose(polygon_area(L_SHAPE), shp.area)
    assert np.array_equal(points_in_polygon(pts, L_SHAPE), np.array([shp.contains(Point(p)) for p in pts]))
    ref = np.array([shp.exterior.distance(Point(p)) for p in pts])
    assert np.allclose(distance_to_edges(pts, L_SHAPE), ref, atol=1e-12)


def test_rectangles_overlap_and_inside_match_shapely():
    rng = np.random.default_rng(1)
    shp = Polygon(L_SHAPE)
    for _ in range(200):
        a = rect_corners(rng.uniform(0, 5, 2), rng.uniform(0.1, 1.0, 2), rng.uniform(-np.pi, np.pi))
        b = rect_corners(rng.uniform(0, 5, 2), rng.uniform(0.1, 1.0, 2), rng.uniform(-np.pi, np.pi))
        pa, pb = Polygon(a), Polygon(b)
        assert pa.is_valid and pa.exterior.is_ccw
        if pa.intersection(pb).area > 1e-9:
            assert polygons_overlap(a, b)
        elif not pa.intersects(pb):
            assert not polygons_overlap(a, b)
        if shp.contains(pa) and shp.exterior.distance(pa) > 1e-9:
            assert polygon_inside(a, L_SHAPE)
        elif not shp.buffer(1e-9).contains(pa):
            assert not polygon_inside(a, L_SHAPE)


def test_simple_angles_collinear():
    assert is_simple(L_SHAPE)
    bow = np.array([[0, 0], [2.0, 2], [2, 0], [0, 2]])
    assert not is_simple(bow) and not Polygon(bow).is_valid
    assert np.allclose(turn_angles_deg(L_SHAPE), 90.0)
    with_mid = np.array([[0, 0], [2.0, 0], [4, 0], [4, 2], [0, 2]])
    assert np.array_equal(remove_collinear(with_mid), with_mid[[0, 2, 3, 4]])
