"""The layout ground truth's native map passes (``native_layout``) against their tensor ops in ``synth.layout``:
exactly equal brackets and edge maps on rendered maps and on random class maps (several transitions per column,
columns without any, two-row maps), for cameras that wrap and that do not."""
import pytest
import torch

from omnidl.cameras import build, resolve_camera
from omnidl.nn import native
from omnidl.synth import layout as L
from omnidl.synth import native_layout, place_camera, render, sample_room

pytestmark = pytest.mark.skipif(native.library() is None, reason="native kernels unavailable")


def _tensor_ops(fn, *args, monkeypatch):
    with monkeypatch.context() as m:
        m.setattr(native_layout, "ENABLED", False)
        return fn(*args)


def _random_maps(H, W, seed):
    g = torch.Generator().manual_seed(seed)
    kind = torch.randint(0, 4, (H, W), generator=g)
    kind[:, :3] = torch.tensor([1, 2, 3]).repeat_interleave(H // 3 + 1)[:H, None]   # ordered columns
    kind[:, 3] = 2                                                                   # a column without transitions
    wall = torch.where(kind == 2, torch.randint(-1, 5, (H, W), generator=g), torch.full((H, W), -1))
    return kind, wall


@pytest.mark.parametrize("H, W, seed", [(2, 7, 0), (5, 9, 1), (48, 96, 2)])
def test_brackets_and_edges_equal_the_tensor_ops_on_random_maps(H, W, seed, monkeypatch):
    kind, wall = _random_maps(H, W, seed)
    fast = L._brackets(kind)
    slow = _tensor_ops(L._brackets, kind, monkeypatch=monkeypatch)
    for a, b in zip(fast, slow):
        assert a.dtype == b.dtype and torch.equal(a, b)
    for wraps in (True, False):
        e = L._edge_map(kind, wall, wraps)
        assert e.dtype == torch.float32 and torch.equal(e, _tensor_ops(L._edge_map, kind, wall, wraps,
                                                                        monkeypatch=monkeypatch)), wraps


@pytest.mark.parametrize("cam", [lambda: build({"type": "equirect", "width": 96, "height": 48}),
                                 lambda: resolve_camera("fisheye_equiangular", 48, 48)])
def test_the_layout_keys_of_a_render_equal_the_tensor_ops(cam, monkeypatch):
    cam = cam()
    sc = sample_room(7)
    pose = place_camera(sc, cam, 7, rotation="random")
    fast = render(sc, cam, pose)
    slow = _tensor_ops(render, sc, cam, pose, monkeypatch=monkeypatch)
    for k in ("boundary", "boundary_valid", "edges", "layout_seg"):
        assert torch.equal(fast[k], slow[k]), k


def test_other_maps_keep_the_tensor_ops():
    assert native_layout.applies(torch.zeros(2, 3, dtype=torch.int64))
    assert not native_layout.applies(torch.zeros(2, 3, dtype=torch.int32))
    assert not native_layout.applies(torch.zeros(1, 3, dtype=torch.int64))
    assert L._brackets(torch.zeros(3, 4, dtype=torch.int8))[0].tolist() == [0, 0, 0, 0]


@pytest.mark.parametrize("call, message", [
    (lambda: native_layout.brackets(torch.zeros(3, 4, dtype=torch.int32)), "kind_map must be an int64 CPU map"),
    (lambda: native_layout.brackets(torch.zeros(1, 4, dtype=torch.int64)), r"shape \(H >= 2, W\)"),
    (lambda: native_layout.edges(torch.zeros(3, 4, dtype=torch.int64), torch.zeros(3, 5, dtype=torch.int64), True),
     r"wall_map must be an int64 CPU map of shape \(3, 4\)"),
])
def test_bad_maps_are_named_errors(call, message):
    with pytest.raises(ValueError, match=message):
        call()
