import math

import pytest
import torch

from omnidl.data.transforms import RandomRotation, horizontal_rotation, rotate_sample, rotate_tensors
from omnidl.geometry.rotations import axis_angle_to_matrix


def _sample(h=16, w=32):
    g = torch.Generator().manual_seed(0)
    return {"image": torch.rand(3, h, w, generator=g), "depth": 1 + torch.rand(1, h, w, generator=g),
            "semantic": torch.randint(0, 14, (h, w), generator=g), "valid": torch.ones(h, w, dtype=torch.bool),
            "meta": {"name": "x"}}


def test_axis_angle_matches_closed_form_pitch():
    a = math.radians(30)
    R = axis_angle_to_matrix(torch.tensor([a, 0.0, 0.0], dtype=torch.float64))
    ref = torch.tensor([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]], dtype=torch.float64)
    assert torch.allclose(R, ref, atol=1e-12)
    R2 = horizontal_rotation(17.0, 90.0)  # azimuth 90 deg: the camera z axis
    assert torch.allclose(R2, axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.radians(17.0)], dtype=torch.float64)),
                          atol=1e-12)
    assert torch.allclose(R2 @ R2.T, torch.eye(3, dtype=torch.float64), atol=1e-12)


def test_zero_rotation_is_identity_and_dtypes_kept():
    s = _sample()
    out = rotate_sample(s, horizontal_rotation(0.0))
    assert torch.allclose(out["image"], s["image"], atol=1e-5)
    assert torch.equal(out["semantic"], s["semantic"]) and out["semantic"].dtype == torch.int64
    assert torch.equal(out["depth"], s["depth"]) and out["valid"].dtype == torch.bool
    assert out["meta"]["name"] == "x" and len(out["meta"]["rotation"]) == 3


def test_labels_stay_labels_and_normals_rotate():
    s = _sample()
    n = torch.tensor([0.0, -1.0, 0.0])  # a floor normal pointing up (y down)
    s["normal"] = n[:, None, None].expand(3, 16, 32).clone()
    R = horizontal_rotation(20.0, "x")
    out = rotate_sample(s, R)
    assert set(out["semantic"].unique().tolist()) <= set(s["semantic"].unique().tolist())
    expect = (R.T.float() @ n)
    assert torch.allclose(out["normal"][:, 8, 16], expect, atol=1e-5)
    # depth (range) values are only moved, never blended
    assert set(out["depth"].unique().tolist()) <= set(s["depth"].unique().tolist())


def test_batched_equals_per_sample():
    s = _sample()
    R = horizontal_rotation(7.0, "z")
    one = rotate_sample(s, R)
    batch = {k: v[None] for k, v in s.items() if isinstance(v, torch.Tensor)}
    many = rotate_tensors(batch, R, batched=True)
    for k in ("image", "depth", "semantic", "valid"):
        assert torch.equal(many[k][0], one[k]), k


def test_unknown_keys_refused_or_dropped():
    s = _sample()
    s["boundary"] = torch.zeros(2, 32)
    with pytest.raises(ValueError, match="boundary"):
        rotate_sample(s, horizontal_rotation(5.0))
    assert "boundary" not in rotate_sample(s, horizontal_rotation(5.0), drop_unknown=True)


class _DS(torch.utils.data.Dataset):
    def __len__(self):
        return 4

    def __getitem__(self, i):
        return _sample()


def test_random_rotation_is_seeded_by_epoch_and_index():
    ds = RandomRotation(_DS(), max_deg=10, seed=3)
    a = [ds.angles(i) for i in range(4)]
    assert a == [ds.angles(i) for i in range(4)]
    assert all(-10 <= ang <= 10 for ang, _ in a) and len({ang for ang, _ in a}) == 4
    ds.set_epoch(1)
    assert [ds.angles(i) for i in range(4)] != a
    assert torch.equal(ds[2]["image"], ds[2]["image"])
