"""The view chain (omnidl.geometry.views): perspective views cut from any camera, aligned on their overlaps and fused
back. A stand-in for the network returns each view's true z-depth (rendered by omnidl.synth from the view's own
pinhole camera) times a random per-view scale; the chain must recover the range map of the input camera."""
from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from omnidl.cameras import Equirectangular, KannalaBrandt, NonCentralPanorama, Unified
from omnidl.geometry.views import (Samples, ThroughViews, align_views, cut_views, depth_through_views, view_layout,
                                   visible_views)

CAMERAS = {
    "equirect": Equirectangular(width=128, height=64),
    "kb195": KannalaBrandt(width=128, height=128, fx=34.0, fy=35.0, cx=64.0, cy=63.0, k0=1.0, k1=-0.01, k2=0.002,
                           k3=-1e-4, k4=1e-6, max_fov=math.radians(195)),
    "mei": Unified(width=128, height=96, xi=0.9, fx=44.0, fy=42.0, s=0.0, cx=62.0, cy=49.0, k1=-0.02, k2=0.002,
                   p1=0.001, p2=-0.0015),
    "noncentral": NonCentralPanorama(width=128, height=64, rc=0.3),
}


def _scene(camera, seed: int = 11):
    from omnidl.synth import place_camera, render, sample_room
    scene = sample_room(seed)
    pose = place_camera(scene, camera, 5)
    return scene, pose, render(scene, camera, pose, layout=False)


def stand_in(scene, pose, log_scales: dict, kind: str = "depth", shifts: dict | None = None):
    """``predict(images, views)``: each view's true z-depth (or inverse depth) rendered from its own pinhole camera at
    the input camera's centre, times ``exp(log_scales[view index])`` (plus ``shifts`` for inverse depth)."""
    from omnidl.synth import render

    def predict(images, views):
        out = []
        for v in views:
            key = tuple(v.rotation.flatten().tolist())
            pv = pose.copy()
            pv[:3, :3] = pose[:3, :3] @ v.rotation.numpy()
            r = render(scene, v.camera, pv, layout=False)
            z = r["depth"][0] * v.camera.unproject_grid().direction[..., 2]
            s = math.exp(log_scales[key])
            out.append(((z * s) if kind == "depth" else (s / z.clamp_min(1e-6) + shifts[key]))[None])
        return torch.stack(out)
    return predict


def _scales(views, seed: int, spread: float = 0.7) -> dict:
    """Random per-view log scales with mean 0 over the views (a metric model whose per-view errors average out)."""
    g = torch.Generator().manual_seed(seed)
    u = torch.empty(len(views), dtype=torch.float64).uniform_(-spread, spread, generator=g)
    u = u - u.mean()
    return {tuple(v.rotation.flatten().tolist()): float(x) for v, x in zip(views, u)}


def _near_edges(d, edge_tol: float = 0.03):
    """``(H, W)`` bool: within 2 px of a depth edge (a neighbour's depth differs by ``edge_tol`` or more)."""
    pad = torch.nn.functional.pad(d[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    nb = torch.stack([pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]])
    edge = ((nb - d).abs() / d.clamp_min(1e-6)).amax(0) >= edge_tol
    return torch.nn.functional.max_pool2d(edge[None, None].float(), 5, 1, 2)[0, 0] > 0


def _errors(res, gt, edge_tol: float = 0.03):
    """Relative errors on valid pixels and on view-border pixels more than 2 px from a depth edge (where a seam would
    show; at depth edges the views' bilinear sampling blends foreground and background)."""
    d, ok = gt["depth"][0], gt["valid"] & (gt["depth"][0] > 0) & res.valid[0]
    rel = (res.depth[0] - d).abs() / d.clamp_min(1e-6)
    smooth = ~_near_edges(d, edge_tol)
    border = ok & res.border[0] & smooth
    return rel[ok], rel[border], float(ok.float().sum() / gt["valid"].float().sum())


def _check_noncentral_coverage(res, gt):
    """Every pixel the panorama's rays see has a value, except some within 2 px of a depth edge (a ray from the rig
    seeing what the centre's views do not: no settled fixed point), under 1 %; the pole rows are all covered."""
    seen = gt["valid"] & (gt["depth"][0] > 0)
    left = seen & ~res.valid[0]
    assert not (left & ~_near_edges(gt["depth"][0])).any(), "a pixel away from depth edges has no value"
    assert float(left.float().sum() / seen.float().sum()) < 0.01
    assert bool(res.valid[0][[0, 1, -2, -1]].all()), "the pole rows"


@pytest.mark.parametrize("layout", ["tangent", "cube"])
@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_view_chain_recovers_depth_with_random_view_scales(name, layout):
    camera = CAMERAS[name]
    scene, pose, gt = _scene(camera)
    views = visible_views(camera, view_layout(layout, size=64))
    res = depth_through_views(gt["image"], camera, stand_in(scene, pose, _scales(views, 1)), views=views, batch=16)
    rel, rel_border, coverage = _errors(res, gt)
    print(f"\n{layout} {name}: {len(views)} views, median rel. error {rel.median():.2e}, border median "
          f"{rel_border.median():.2e} max {rel_border.max():.2e}, coverage {coverage:.3f}")
    assert rel.median() < 0.01
    assert rel_border.median() < 0.01
    assert rel_border.max() < 0.05, "a seam along a view border"
    assert coverage > 0.99
    if name == "noncentral":
        _check_noncentral_coverage(res, gt)


def test_noncentral_rig_wider_than_the_pole_cone():
    """``rc = 1`` m: the points 3 m along view rays within 70.5 deg latitude of the poles lie inside the rig's
    cylinder; the cut samples them farther along the ray (every view pixel valid), and the fused range covers every
    pixel but some on depth edges, as accurate as elsewhere."""
    camera = NonCentralPanorama(width=128, height=64, rc=1.0)
    scene, pose, gt = _scene(camera)
    views = view_layout("tangent", size=64)
    assert bool(cut_views(gt["image"], camera, views)[1].all())
    res = depth_through_views(gt["image"], camera, stand_in(scene, pose, _scales(views, 1)), views=views, batch=16)
    rel, rel_border, _ = _errors(res, gt)
    assert rel.median() < 0.01 and rel_border.median() < 0.01
    _check_noncentral_coverage(res, gt)


def test_affine_inverse_depth_is_aligned():
    """Views that predict ``s_k / z + t_k`` (an affine-invariant inverse depth) fuse to the range up to one global
    scale."""
    camera = CAMERAS["equirect"]
    scene, pose, gt = _scene(camera)
    views = view_layout("cube", size=64)
    g = torch.Generator().manual_seed(3)
    shifts = {tuple(v.rotation.flatten().tolist()): float(torch.rand(1, generator=g)) * 0.2 for v in views}
    res = depth_through_views(gt["image"], camera, stand_in(scene, pose, _scales(views, 2, 0.3), "disparity", shifts),
                              views=views, kind="disparity", align="affine", batch=16)
    ok = res.valid[0] & gt["valid"]
    ratio = res.depth[0][ok] / gt["depth"][0][ok]
    rel = (ratio / ratio.median() - 1).abs()
    assert rel.median() < 0.01


@settings(max_examples=25, deadline=None, derandomize=True)
@given(V=st.integers(2, 8), seed=st.integers(0, 10_000))
def test_scale_alignment_recovers_random_scales(V, seed):
    g = torch.Generator().manual_seed(seed)
    P = 400
    valid = torch.rand(V, P, generator=g) < 0.6
    valid[:, :V] |= torch.eye(V, dtype=torch.bool)          # every view sees something
    chain = torch.arange(V - 1)
    valid[chain, V + chain] = True                          # a chain of overlaps: the views are connected
    valid[chain + 1, V + chain] = True
    r = 1 + 4 * torch.rand(P, generator=g, dtype=torch.float64)
    cos = 0.2 + 0.8 * torch.rand(V, P, generator=g, dtype=torch.float64)
    u = torch.randn(V, generator=g, dtype=torch.float64) * 0.5
    value = torch.where(valid, torch.exp(-u)[:, None] * r * cos, torch.zeros(V, P, dtype=torch.float64))
    al = align_views(Samples(value, cos, valid.double(), valid), "depth", "scale")
    est = al.scale.log()
    torch.testing.assert_close(est - est.mean(), u - u.mean(), atol=1e-9, rtol=0)


def test_layouts_cover_the_sphere_with_overlap():
    d = torch.nn.functional.normalize(torch.randn(4000, 3, generator=torch.Generator().manual_seed(0),
                                                  dtype=torch.float64), dim=-1)
    for layout in ("tangent", "cube"):
        views = view_layout(layout, size=32)
        seen = torch.stack([v.camera.project(d @ v.rotation)[1] for v in views])
        assert bool(seen.any(0).all()), f"{layout}: a direction no view sees"
        assert float((seen.sum(0) >= 2).float().mean()) > 0.15, f"{layout}: too little overlap"


def test_bad_arguments_are_named():
    cam = CAMERAS["equirect"]
    img = torch.rand(3, cam.height, cam.width)
    with pytest.raises(ValueError, match="layout"):
        view_layout("octahedron")
    with pytest.raises(ValueError, match="fov"):
        view_layout("cube", fov=90)
    with pytest.raises(ValueError, match="expected \\(n, 1, S, S\\)"):
        depth_through_views(img, cam, lambda x, v: x, layout="cube", size=16)
    with pytest.raises(ValueError, match="kind"):
        depth_through_views(img, cam, lambda x, v: x[:, :1], kind="height")
    with pytest.raises(ValueError, match="non-finite"):
        depth_through_views(img, cam, lambda x, v: x[:, :1] * math.nan, layout="cube", size=16)


class _StandIn(torch.nn.Module):
    """A stand-in network: z-depth ``2 * (1 + blue) * cos`` (a sphere of radius 2 m around the centre where the
    image has no blue) and 3 class logits (red, green, 0)."""

    def __init__(self) -> None:
        super().__init__()
        self.scale = torch.nn.Parameter(torch.ones(()))

    def forward(self, x):
        from omnidl.geometry.views import view_cos
        S = x.shape[-1]
        cos = view_cos(view_layout("cube", size=S)[0], torch.float32)
        depth = 2 * self.scale * cos * (1 + x[:, 2:3])
        sem = torch.stack([x[:, 0], x[:, 1], torch.zeros_like(x[:, 0])], 1)
        return {"depth": depth, "semantic": sem}


def test_through_views_runs_the_chain_the_same_in_every_mode():
    """ThroughViews always runs the chain (no route on size or mode): train, eval and no_grad give the same
    outputs, none with a gradient, equal to a direct depth_through_views call on the camera resized to the image."""
    camera = {"type": "equirect", "width": 64, "height": 32}
    net = ThroughViews(_StandIn(), camera, layout="cube", size=16)
    assert list(net.state_dict()) == ["net.scale"] and net.training
    img = torch.rand(2, 3, 16, 32, generator=torch.Generator().manual_seed(0))
    train = net(img)                                 # a 32 x 16 image: the camera resized
    net.eval()
    evaluated = net(img)
    with torch.no_grad():
        no_grad = net(img)
    assert train["depth"].shape == (2, 1, 16, 32) and train["semantic"].shape == (2, 3, 16, 32)
    for out in (evaluated, no_grad):
        for key in ("depth", "semantic"):
            torch.testing.assert_close(out[key], train[key], rtol=0, atol=0)
    assert not train["depth"].requires_grad and not train["semantic"].requires_grad
    cam = Equirectangular(width=32, height=16)
    for b in range(2):
        direct = depth_through_views(img[b], cam, lambda x, v: net.net(x)["depth"], layout="cube", size=16)
        torch.testing.assert_close(train["depth"][b], direct.depth, rtol=1e-6, atol=1e-6)
    green = torch.zeros(1, 3, 16, 32)
    green[:, 1] = 1.0                                # class 1 everywhere, no blue: the 2 m sphere
    out = net(green)
    torch.testing.assert_close(out["depth"], torch.full((1, 1, 16, 32), 2.0), rtol=0.01, atol=0)  # bilinear z of 16 px views
    assert bool((out["semantic"].argmax(1) == 1).all())
    with pytest.raises(ValueError, match="16x16"):  # a views-sized input is not a view: it is an image of the camera
        net(torch.rand(1, 3, 16, 16))
    with pytest.raises(ValueError, match="align"):
        ThroughViews(_StandIn(), camera, align="affine")
    with pytest.raises(ValueError, match="input must be images"):
        net(torch.rand(3, 16, 32))
