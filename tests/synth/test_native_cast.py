"""The renderer's native box slab tests (``native_cast``) against the tensor-op loop of ``raycast.cast_boxes``:
ranges and box ids bit for bit, for central and non-central rays, every culling mode, axis-aligned and degenerate
directions (zero and NaN components) and ties between batches."""
import sys

import numpy as np
import pytest
import torch

from omnidl.cameras import build
from omnidl.nn import native
from omnidl.synth import native_cast, place_camera, sample_room
from omnidl.synth import raycast as RC
from omnidl.synth.tiles import ray_tiles, tile_batches, tile_mask

pytestmark = pytest.mark.skipif(native.library() is None, reason="native kernels unavailable")

CAMERAS = {
    "equirect": lambda: build({"type": "equirect", "width": 96, "height": 48}),
    "noncentral_pano": lambda: build({"type": "noncentral_pano", "width": 96, "height": 48, "rc": 0.8}),
}


def _scene_rays(name, seed, rotation="random"):
    cam = CAMERAS[name]()
    sc = sample_room(seed)
    pose = place_camera(sc, cam, seed, rotation=rotation)
    o, d, _ = sys.modules["omnidl.synth.render"].world_rays(cam, pose)
    boxes = torch.as_tensor(sc.boxes, dtype=torch.float32)
    inst = sc.boxes[:, 8].astype(np.int64)
    groups = [torch.as_tensor(np.nonzero(inst == i)[0]) for i in np.unique(inst)]
    centre = torch.as_tensor(pose[:3, 3], dtype=torch.float32)
    return cam, pose, o, d, boxes, groups, centre


def _both(monkeypatch, *args, **kw):
    calls = []
    real = native_cast.box_slabs
    monkeypatch.setattr(native_cast, "box_slabs", lambda *a: calls.append(1) or real(*a))
    fast = RC.cast_boxes(*args, **kw)
    assert calls, "the native slab tests did not run"
    monkeypatch.setattr(native_cast, "ENABLED", False)
    slow = RC.cast_boxes(*args, **kw)
    monkeypatch.setattr(native_cast, "ENABLED", True)
    return fast, slow


def _assert_bits(fast, slow, what):
    assert torch.equal(fast[0], slow[0]), (what, int((fast[0] != slow[0]).sum()))
    assert torch.equal(fast[1], slow[1]), (what, int((fast[1] != slow[1]).sum()))


@pytest.mark.parametrize("name", list(CAMERAS))
@pytest.mark.parametrize("seed", [3, 10])
def test_every_culling_mode_gives_the_tensor_paths_bits(name, seed, monkeypatch):
    cam, pose, o, d, boxes, groups, centre = _scene_rays(name, seed)
    far = torch.full((d.shape[0],), float("inf"))
    rig = float((o - centre).norm(dim=-1).max())
    tiles = ray_tiles(cam)
    pose64 = torch.as_tensor(pose)
    near = tile_mask(tiles, *RC.group_spheres(boxes, groups), pose64[:3, :3], pose64[:3, 3])
    joined = tile_batches(tiles, near, [len(g) for g in groups])
    batches = [torch.cat([groups[i] for i in gs]) for gs, _ in joined]
    room_t = torch.full_like(far, 4.0)                       # some rays are closer to a wall than to any box
    tiled = {"candidates": [r for _, r in joined]}
    for what, args, kw in [("tiles", (o, d, boxes, batches, room_t, centre, rig), tiled),
                           ("per-ray culling", (o, d, boxes, groups, far, centre, rig), {}),
                           ("no culling", (o, d, boxes, groups, far, centre, rig), {"cull": False})]:
        _assert_bits(*_both(monkeypatch, *args, **kw), f"{name} {seed} {what}")


def test_axis_aligned_and_degenerate_directions(monkeypatch):
    """Direction components of exactly 0 (the safe inverse's 1e-12), tiny ones and NaN rays."""
    _, _, o, d, boxes, groups, centre = _scene_rays("equirect", 4, "upright")
    d = d.clone()
    d[::7, 0] = 0.0
    d[1::7, 1] = 0.0
    d[2::7, 2] = 0.0
    d[3::7, :2] = 0.0
    d[4::7, 2] = 1e-13
    d[5::7, 1] = -1e-13
    d[6::97] = float("nan")
    boxes = boxes.clone()
    boxes[::3, 6] = 0.0                                      # axis-aligned boxes: exact zeros in the frames
    far = torch.full((d.shape[0],), float("inf"))
    fast, slow = _both(monkeypatch, o, d, boxes, groups, far, centre, 0.0, cull=False)
    _assert_bits(fast, slow, "degenerate")
    assert (fast[1] >= 0).any() and (fast[1][6::97] == -1).all()


def test_ties_go_to_the_earlier_batch_and_box(monkeypatch):
    _, _, o, d, boxes, groups, centre = _scene_rays("equirect", 3, "upright")
    dup = torch.cat([boxes, boxes[:4], boxes[:4]])            # two copies: a later batch and the same batch
    n = len(boxes)
    groups = [torch.arange(n, n + 4)] + groups + [torch.cat([torch.arange(n + 4, n + 8), torch.arange(4)])]
    far = torch.full((d.shape[0],), float("inf"))
    fast, slow = _both(monkeypatch, o, d, dup, groups, far, centre, 0.0, cull=False)
    _assert_bits(fast, slow, "ties")
    assert ((fast[1] >= n) & (fast[1] < n + 4)).any() and not (fast[1] >= n + 4).any()


def test_empty_batches_and_no_boxes(monkeypatch):
    _, _, o, d, boxes, groups, centre = _scene_rays("noncentral_pano", 5)
    far = torch.full((d.shape[0],), float("inf"))
    cands = [torch.zeros(0, dtype=torch.int64)] * len(groups)
    cands[1] = torch.arange(0, d.shape[0], 3)
    _assert_bits(*_both(monkeypatch, o, d, boxes, groups, far, centre, 1.0, candidates=cands), "sparse")
    empty = [torch.zeros(0, dtype=torch.int64)] + groups[1:]
    _assert_bits(*_both(monkeypatch, o, d, boxes, empty, far, centre, 1.0, cull=False), "an empty group")
    t, ids = RC.cast_boxes(o, d, boxes[:0], [], far, centre, 1.0)
    assert torch.isinf(t).all() and (ids == -1).all()


def test_the_tensor_path_runs_for_float64(monkeypatch):
    _, _, o, d, boxes, groups, centre = _scene_rays("equirect", 3)
    monkeypatch.setattr(native_cast, "box_slabs", lambda *a: pytest.fail("native slab tests ran"))
    assert not native_cast.applies(d.double())
    far = torch.full((d.shape[0],), float("inf"), dtype=torch.float64)
    RC.cast_boxes(o.double(), d.double(), boxes.double(), groups, far, centre.double(), 0.0)


def _good(P=6, B=2):
    return dict(origin=torch.zeros(1, 3), direction=torch.ones(P, 3), boxes=torch.zeros(B, 9),
                groups=[torch.tensor([0, 1])], rays=[torch.arange(P)], t_best=torch.full((P,), 9.0),
                box_id=torch.full((P,), -1))


@pytest.mark.parametrize("field, value, message", [
    ("origin", torch.zeros(2, 3), r"origin must be .*1 or 6 rows"),
    ("direction", torch.ones(6, 3, dtype=torch.float64), "direction must be a float32"),
    ("boxes", torch.zeros(2, 8), r"boxes must be .* shape \(2, 9\)"),
    ("t_best", torch.zeros(5), r"t_best must be .* shape \(6,\)"),
    ("box_id", torch.zeros(6, dtype=torch.int32), "box_id must be contiguous"),
    ("rays", [torch.arange(6), torch.arange(2)], "1 box groups but 2 ray lists"),
    ("groups", [torch.tensor([0, 2])], r"box indices must lie in \[0, 2\)"),
    ("rays", [torch.tensor([6])], r"ray indices must lie in \[0, 6\)"),
])
def test_bad_operands_are_named_errors(field, value, message):
    kw = _good()
    kw[field] = value
    with pytest.raises(ValueError, match=message):
        native_cast.box_slabs(**kw)
