import math

import torch

from omnidl.postprocess.gyroscope.icosahedron import icosahedron_faces, icosahedron_vertices, mean_edge_angle


def test_vertex_counts_and_unit_norm():
    for n in range(5):
        v = icosahedron_vertices(n, torch.float64)
        assert v.shape == (10 * 4 ** n + 2, 3)
        assert torch.allclose(v.norm(dim=-1), torch.ones(len(v), dtype=torch.float64))
        assert icosahedron_faces(n).shape == (20 * 4 ** n, 3)
        # no duplicated vertices
        d = torch.cdist(v, v) + 10 * torch.eye(len(v), dtype=torch.float64)
        assert d.min() > 0.5 * mean_edge_angle(n)


def test_level0_is_the_regular_icosahedron():
    v = icosahedron_vertices(0, torch.float64)
    target = torch.tensor([-0.525731, 0.850651, 0.0], dtype=torch.float64)
    assert (v - target).norm(dim=-1).min() < 1e-6
    cos = v @ v.T
    # every vertex has exactly 5 neighbours at the icosahedron's edge angle (63.43 deg)
    edge = math.cos(math.atan(2.0))
    assert ((cos - edge).abs() < 1e-9).sum(-1).eq(5).all()


def test_edge_lengths_halve_per_level():
    assert abs(mean_edge_angle(0) - math.atan(2.0)) < 1e-12  # regular icosahedron edge angle
    for n in range(4):
        ratio = mean_edge_angle(n) / mean_edge_angle(n + 1)
        assert 1.8 < ratio < 2.1
    # libPeR's table (edge chords 0.55269, 0.27635, 0.13817 for n = 1..3) agrees to ~10 %
    for n, chord in [(1, 0.55269), (2, 0.27635), (3, 0.13817)]:
        assert abs(mean_edge_angle(n) - chord) / chord < 0.12
