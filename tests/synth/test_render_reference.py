"""The fast renderer against the renderer before the issue-17 speed work (tests/reference/synth_renderer.py).

Every output key is compared: integer and boolean maps exactly, float maps to 1e-5 absolute plus 1e-5 relative
(on the machine the speed work was done on they are bit-identical; the tolerance only absorbs a CPU whose
kernels round differently: on an AVX-512 host a fisheye image differed by 1.04e-5 at a pixel). The pieces that make the renderer fast are checked on their own:
the replayed layout bisection against the casting one, the tile culling against testing every ray.
"""
import sys

import numpy as np
import pytest
import torch

from omnidl.cameras import build, resolve_camera
from omnidl.synth import place_camera, render, sample_room
from omnidl.synth import layout as L
from omnidl.synth import raycast as RC
from tests.reference.synth_renderer import render_reference
from omnidl.synth.tiles import ray_tiles, tile_batches, tile_candidates, tile_mask

CAMERAS = {
    "equirect": lambda: build({"type": "equirect", "width": 128, "height": 64}),
    "noncentral_pano": lambda: build({"type": "noncentral_pano", "width": 128, "height": 64, "rc": 0.8}),
    "fisheye": lambda: resolve_camera("fisheye_equiangular", 64, 64),
    "pinhole": lambda: build({"type": "pinhole", "width": 64, "height": 48, "fx": 40.0, "fy": 40.0,
                              "cx": 32.0, "cy": 24.0}),
}


def _assert_same(a: dict, b: dict, what: str) -> None:
    assert a.keys() == b.keys(), what
    assert a["meta"] == b["meta"], what
    for k, va in a.items():
        if k == "meta":
            continue
        vb = b[k]
        assert va.dtype == vb.dtype and va.shape == vb.shape, (what, k)
        if va.is_floating_point():
            assert torch.allclose(va, vb, rtol=1e-5, atol=1e-5), (what, k, (va - vb).abs().max().item())
        else:
            assert torch.equal(va, vb), (what, k, int((va != vb).sum()))


@pytest.mark.parametrize("name", list(CAMERAS))
@pytest.mark.parametrize("seed", [3, 11])
def test_every_output_key_matches_the_previous_renderer(name, seed):
    cam = CAMERAS[name]()
    sc = sample_room(seed)
    for rotation in ("upright", "random"):
        pose = place_camera(sc, cam, seed, rotation=rotation)
        _assert_same(render(sc, cam, pose), render_reference(sc, cam, pose), f"{name} {seed} {rotation}")


@pytest.mark.parametrize("kw", [{"dtype": torch.float64}, {"shadows": True}, {"layout": False}])
def test_options_match_the_previous_renderer(kw):
    for name in ("equirect", "noncentral_pano"):
        cam = CAMERAS[name]()
        sc = sample_room(5)
        pose = place_camera(sc, cam, 5)
        _assert_same(render(sc, cam, pose, **kw), render_reference(sc, cam, pose, **kw), f"{name} {kw}")


@pytest.mark.parametrize("name", ["equirect", "noncentral_pano", "pinhole"])
def test_replayed_bisection_equals_the_casting_one_bitwise(name):
    """Upright columns: the bisection replayed against the projected edge (one verifying cast) gives the
    bits of the 7 casting rounds; the replay is actually taken (no fallback)."""
    cam = CAMERAS[name]()
    for seed in (1, 2, 7):
        sc = sample_room(seed)
        pose = place_camera(sc, cam, seed)
        out = render(sc, cam, pose)
        kind_map = out["layout_seg"]
        fast = L.column_boundaries(sc, cam, pose, kind_map, vertical_columns=True)
        slow = L.column_boundaries(sc, cam, pose, kind_map, vertical_columns=False)
        assert torch.equal(fast[0], slow[0]) and torch.equal(fast[1], slow[1])
        R = torch.as_tensor(pose[:3, :3])
        t = torch.as_tensor(pose[:3, 3])
        poly = torch.as_tensor(sc.polygon)
        assert L._edge_rows(sc, cam, R, t, poly, fast[1].reshape(-1)) is not None


def test_a_wrong_edge_falls_back_to_the_casting_rounds(monkeypatch):
    """The verifying cast catches a replay against a wrong transition and the casting rounds take over."""
    cam = CAMERAS["equirect"]()
    sc = sample_room(4)
    pose = place_camera(sc, cam, 4)
    kind_map = render(sc, cam, pose)["layout_seg"]
    slow = L.column_boundaries(sc, cam, pose, kind_map)
    good = L._edge_rows
    monkeypatch.setattr(L, "_edge_rows", lambda *a: good(*a) + 0.3)
    fast = L.column_boundaries(sc, cam, pose, kind_map, vertical_columns=True)
    assert torch.equal(fast[0], slow[0])


@pytest.mark.parametrize("name", list(CAMERAS))
def test_tile_candidates_hold_every_ray_that_hits_a_group(name):
    cam = CAMERAS[name]()
    for seed in (3, 6):
        sc = sample_room(seed)
        pose = place_camera(sc, cam, seed, rotation="random")
        o, d, _ = sys.modules["omnidl.synth.render"].world_rays(cam, pose)
        boxes = torch.as_tensor(sc.boxes, dtype=torch.float32)
        inst = sc.boxes[:, 8].astype(np.int64)
        groups = [torch.as_tensor(np.nonzero(inst == i)[0]) for i in np.unique(inst)]
        mids, radius = RC.group_spheres(boxes, groups)
        pose64 = torch.as_tensor(pose)
        cands = tile_candidates(ray_tiles(cam), mids, radius, pose64[:3, :3], pose64[:3, 3])
        far = torch.full((d.shape[0],), float("inf"))
        centre = torch.as_tensor(pose[:3, 3], dtype=torch.float32)
        for gi, g in enumerate(groups):
            t_all, _ = RC.cast_boxes(o, d, boxes, [g], far, centre, 0.0, cull=False)
            hit = torch.isfinite(t_all).nonzero()[:, 0]
            assert torch.isin(hit, cands[gi]).all(), (name, seed, gi)
        # and the nearest hits are the bits of the per-ray culling
        ref = RC.cast_boxes(o, d, boxes, groups, far, centre, 1.0)
        got = RC.cast_boxes(o, d, boxes, groups, far, centre, 1.0, candidates=cands)
        assert torch.equal(ref[0], got[0]) and torch.equal(ref[1], got[1])


def test_batched_groups_give_the_bits_of_one_pass_per_group():
    """Consecutive groups joined into one slab pass (any slack) give the per-group result; exact ties
    (a duplicated box in a later group) still go to the earlier group."""
    cam = CAMERAS["equirect"]()
    sc = sample_room(3)
    pose = place_camera(sc, cam, 3)
    o, d, _ = sys.modules["omnidl.synth.render"].world_rays(cam, pose)
    dup = np.concatenate([sc.boxes, sc.boxes[:4]])
    dup[len(sc.boxes):, 8] = dup[:, 8].max() + 1                 # the copies form the last object
    boxes = torch.as_tensor(dup, dtype=torch.float32)
    inst = dup[:, 8].astype(np.int64)
    groups = [torch.as_tensor(np.nonzero(inst == i)[0]) for i in np.unique(inst)]
    # the copies first: they must win every tie against the originals, which come later
    groups = groups[-1:] + groups[:-1]
    far = torch.full((d.shape[0],), float("inf"))
    centre = torch.as_tensor(pose[:3, 3], dtype=torch.float32)
    ref = RC.cast_boxes(o, d, boxes, groups, far, centre, 0.0)
    assert (ref[1] >= len(sc.boxes)).any()                          # ties happened and the copies won them
    tiles = ray_tiles(cam)
    pose64 = torch.as_tensor(pose)
    near = tile_mask(tiles, *RC.group_spheres(boxes, groups), pose64[:3, :3], pose64[:3, 3])
    for slack in (-10 ** 9, 0, 4096, 10 ** 9):
        joined = tile_batches(tiles, near, [len(g) for g in groups], slack)
        if slack == 10 ** 9:
            assert len(joined) == 1
        batches = [torch.cat([groups[i] for i in gs]) for gs, _ in joined]
        got = RC.cast_boxes(o, d, boxes, batches, far, centre, 0.0, candidates=[r for _, r in joined])
        assert torch.equal(ref[0], got[0]) and torch.equal(ref[1], got[1]), slack


def test_a_room_without_objects_matches_the_previous_renderer():
    for name in ("equirect", "noncentral_pano"):
        cam = CAMERAS[name]()
        sc = sample_room(2, furniture=False)
        pose = place_camera(sc, cam, 2)
        _assert_same(render(sc, cam, pose), render_reference(sc, cam, pose), name)
