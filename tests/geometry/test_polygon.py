"""2-D polygon helpers (omnidl.geometry.polygon) against shapely and closed forms."""
import numpy as np
import pytest
from shapely.geometry import LinearRing, Point, Polygon

from omnidl.geometry.polygon import (distance_to_edges, is_simple, points_in_polygon, polygon_area, polygon_inside,
                                    polygon_intersection_area, polygons_overlap, ray_line_range, ray_polygon_hit,
                                    rect_corners, remove_collinear, segments_intersect, turn_angles_deg)

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


# --- areas, intersections and predicates of random polygons against shapely --------------------------------

def _random_star(rng, n, centre=(0.0, 0.0)):
    """A random simple (star-shaped) counter-clockwise polygon."""
    ang = np.sort(rng.uniform(0, 2 * np.pi, n))
    r = rng.uniform(1.0, 4.0, n)
    return np.stack([centre[0] + r * np.cos(ang), centre[1] + r * np.sin(ang)], 1)


@pytest.mark.parametrize("seed", range(8))
def test_random_polygons_area_intersection_contains_match_shapely(seed):
    rng = np.random.default_rng(100 + seed)
    p = _random_star(rng, int(rng.integers(3, 14)))
    q = _random_star(rng, int(rng.integers(3, 14)), centre=rng.uniform(-2, 2, 2))
    if seed % 2:
        q = q[::-1]                                     # clockwise: negative area, same intersection
    sp, sq = Polygon(p), Polygon(q)
    assert polygon_area(p) == pytest.approx(sp.area, rel=1e-12)
    assert polygon_area(q) == pytest.approx(sq.area if seed % 2 == 0 else -sq.area, rel=1e-12)
    ref = sp.intersection(sq).area
    assert polygon_intersection_area(p, q) == pytest.approx(ref, rel=1e-9, abs=1e-12)
    assert polygon_intersection_area(q, p) == pytest.approx(ref, rel=1e-9, abs=1e-12)
    assert polygon_intersection_area(p, p) == pytest.approx(sp.area, rel=1e-12)
    assert is_simple(p) and is_simple(q) and sp.is_valid and sq.is_valid
    pts = rng.uniform(-6, 6, size=(300, 2))
    assert np.array_equal(points_in_polygon(pts, q), np.array([sq.contains(Point(x)) for x in pts]))
    assert polygons_overlap(p, q) == (ref > 0)


def test_is_simple_matches_shapely_on_random_vertex_orders():
    rng = np.random.default_rng(7)
    seen = set()
    for _ in range(300):
        poly = rng.uniform(0, 1, size=(int(rng.integers(4, 9)), 2))
        ref = LinearRing(poly).is_simple
        assert is_simple(poly) == ref == Polygon(poly).is_valid
        assert is_simple(poly, eps=0.0) == ref
        seen.add(ref)
    assert seen == {True, False}


def test_segments_intersect_broadcasts_and_ignores_touching():
    p1, p2 = np.array([0.0, 0]), np.array([2.0, 2])
    q1 = np.array([[0.0, 2], [3, 0], [1, 1], [2, 2]])
    q2 = np.array([[2.0, 0], [3, 3], [2, 0], [3, 0]])
    assert segments_intersect(p1, p2, q1, q2).tolist() == [True, False, False, False]   # cross, miss, touch, share end


def test_zero_length_edge_only_allowed_with_eps_zero():
    square = np.array([[0.0, 0], [1, 0], [1, 1], [1, 1], [0, 1]])      # repeated vertex
    assert not is_simple(square) and is_simple(square, eps=0.0)
    assert not is_simple(square[:2])


# --- closed forms --------------------------------------------------------------------------------------------

def test_closed_form_areas():
    square = np.array([[-1.0, -1], [1, -1], [1, 1], [-1, 1]])
    assert polygon_area(square) == 4.0 and polygon_area(square[::-1]) == -4.0
    assert polygon_area(square[:2]) == 0.0
    assert polygon_intersection_area(square, square + [1.0, 1.0]) == pytest.approx(1.0)
    assert polygon_intersection_area(square, square + [3.0, 0.0]) == 0.0
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    diamond = square @ np.array([[c, -s], [s, c]]).T
    # a square and the same square turned by 45 degrees meet in the regular octagon of inradius 1
    assert polygon_intersection_area(square, diamond) == pytest.approx(8 * (np.sqrt(2) - 1), rel=1e-12)
    assert polygon_intersection_area(L_SHAPE, np.array([[1.0, 1], [3, 1], [3, 3], [1, 3]])) == pytest.approx(3.0)


def test_ray_polygon_hit_closed_form():
    square = np.array([[-1.0, -1], [1, -1], [1, 1], [-1, 1]])
    origin = np.array([[0.0, 0], [0, 0], [0.5, 0], [5, 5]])
    direction = np.array([[1.0, 0], [0, -2], [-1, 0], [1, 0]])
    s, k = ray_polygon_hit(square, origin, direction)
    assert np.allclose(s[:3], [1.0, 0.5, 1.5]) and k[:3].tolist() == [1, 0, 3]
    assert s[3] == np.inf
    # from outside, the first of the two edges on the ray
    s, k = ray_polygon_hit(square, np.array([[-3.0, 0]]), np.array([[1.0, 0]]))
    assert s[0] == pytest.approx(2.0) and k[0] == 3


def test_ray_line_range_closed_form():
    theta, d = 0.0, 2.0                     # the line y = 2 (normal (0, 1))
    o = np.array([[0.0, 0], [0, 0], [0, 0], [0, 3]])
    b = np.array([[0.0, 1], [1, 1], [1, 0], [0, 1]])
    assert np.allclose(ray_line_range(theta, d, o, b), [2.0, 2.0, np.nan, -1.0], equal_nan=True)
    assert np.allclose(ray_line_range(theta, d, o, b, facing=True), [2.0, 2.0, np.nan, np.nan], equal_nan=True)
    # a wall line seen from the origin: the range along the ray to its foot point is d
    th = np.linspace(-3, 3, 7)
    foot = np.stack([-np.sin(th), np.cos(th)], -1)
    assert np.allclose(ray_line_range(th, 1.5, np.zeros((7, 2)), foot), 1.5)
