"""``--max-points`` / ``--voxel`` (:mod:`omnidl.apps.predict.points`): bounded, deterministic, faithful."""
from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from omnidl.apps.predict.points import CloudOptions, stride_subsample, subsample, voxel_downsample


def test_voxel_mean_per_cell_and_stride():
    pts = torch.tensor([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [1.2, 0.0, 0.0]])
    cols = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.5, 0.5, 0.5]])
    p, c = voxel_downsample(pts, cols, 1.0)
    assert torch.allclose(p, torch.tensor([[0.2, 0.2, 0.2], [1.2, 0.0, 0.0]]))
    assert torch.allclose(c, torch.tensor([[0.5, 0.5, 0.5], [0.5, 0.5, 0.5]]))
    p, _ = stride_subsample(torch.arange(30.0).reshape(10, 3), None, 4)
    assert p[:, 0].tolist() == [0.0, 6.0, 15.0, 21.0]                 # indices floor(k * 10 / 4)
    with pytest.raises(ValueError, match="--max-points"):
        CloudOptions(max_points=2.5)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(n=st.integers(0, 400), max_points=st.integers(0, 120), voxel=st.sampled_from([0.0, 0.05, 0.3, 2.0]),
       seed=st.integers(0, 2**16))
def test_subsample_is_bounded_deterministic_and_stays_in_the_cloud(n, max_points, voxel, seed):
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(n, 3, generator=g) * 4 - 2
    cols = torch.rand(n, 3, generator=g)
    opts = CloudOptions(max_points=max_points, voxel=voxel)
    p1, c1 = subsample(pts, cols, opts)
    p2, c2 = subsample(pts.clone(), cols.clone(), opts)
    assert torch.equal(p1, p2) and torch.equal(c1, c2)                 # deterministic
    assert len(p1) == len(c1) <= n and (max_points == 0 or len(p1) <= max_points)
    if voxel == 0 and max_points == 0:
        assert torch.equal(p1, pts)                                    # the default keeps every point
    if n:
        lo, hi = pts.min(0).values, pts.max(0).values
        assert ((p1 >= lo - 1e-5) & (p1 <= hi + 1e-5)).all()          # means of real points
    if voxel > 0 and max_points == 0 and n:
        cells = torch.unique(torch.floor(pts.double() / voxel).long(), dim=0)
        assert len(p1) == len(cells)                                   # one point per occupied voxel
        assert torch.equal(torch.unique(torch.floor(p1.double() / voxel).long(), dim=0), cells)
