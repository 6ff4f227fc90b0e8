"""Ray caster: depth consistency (unprojected hits lie on the surfaces), boundaries vs projected layout
lines, normals, determinism, any camera."""
import dataclasses
import math

import numpy as np
import pytest
import torch

from omnidl.cameras import build
from omnidl.classes import CLASS_ID
from omnidl.synth import place_camera, render, sample_room
from omnidl.geometry.rotations import rotation_z, upright_to_world

CAMERAS = {
    "equirect": {"type": "equirect", "width": 128, "height": 64},
    "noncentral_pano": {"type": "noncentral_pano", "width": 128, "height": 64, "rc": 0.7},
}


def _box_sdf(p, box):
    """Signed distance of points (K, 3) to a yaw-rotated box row [cx cy cz hx hy hz yaw ...]."""
    c, s = math.cos(box[6]), math.sin(box[6])
    q = p - box[:3]
    local = np.stack([c * q[:, 0] + s * q[:, 1], -s * q[:, 0] + c * q[:, 1], q[:, 2]], -1)
    d = np.abs(local) - box[3:6]
    outside = np.linalg.norm(np.maximum(d, 0), axis=-1)
    inside = np.minimum(d.max(-1), 0)
    return outside + inside


def _world_points(cam, pose, depth):
    H, W = depth.shape
    rays = cam.unproject_grid(dtype=torch.float64)
    pts = rays.at(torch.as_tensor(depth, dtype=torch.float64)).reshape(-1, 3).numpy()
    return pts @ pose[:3, :3].T + pose[:3, 3]


@pytest.mark.parametrize("name", list(CAMERAS))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_depth_lands_on_the_surface_hit(name, dtype):
    cam = build(CAMERAS[name])
    for seed in (1, 2):
        sc = sample_room(seed)
        pose = place_camera(sc, cam, seed)
        out = render(sc, cam, pose, dtype=dtype, layout=False)
        depth = out["depth"][0].numpy().astype(np.float64)
        valid = out["valid"].numpy().reshape(-1)
        assert valid.all()  # full panoramas see the scene everywhere
        p = _world_points(cam, pose, depth)
        sem = out["semantic"].numpy().reshape(-1)
        inst = out["instance"].numpy().reshape(-1)
        err = np.full(len(p), np.inf)
        err[sem == CLASS_ID["floor"]] = np.abs(p[sem == CLASS_ID["floor"], 2])
        err[sem == CLASS_ID["ceiling"]] = np.abs(p[sem == CLASS_ID["ceiling"], 2] - sc.height)
        poly = sc.polygon
        walls = np.isin(sem, [CLASS_ID[c] for c in ("wall", "door", "window", "board")]) & (inst <= sc.num_walls) | \
            np.isin(inst, sc.decals[:, 6].astype(int))
        for k in range(sc.num_walls):
            a, b = poly[k], poly[(k + 1) % len(poly)]
            e = (b - a) / np.linalg.norm(b - a)
            n = np.array([-e[1], e[0]])
            dist = np.abs((p[:, :2] - a) @ n)
            err[walls] = np.minimum(err[walls], dist[walls])
        for i in np.unique(sc.boxes[:, 8]).astype(int):
            m = inst == i
            if m.any():
                err[m] = np.min([np.abs(_box_sdf(p[m], bx)) for bx in sc.boxes[sc.boxes[:, 8] == i]], axis=0)
        assert np.isfinite(err).all()
        assert err.max() < 1e-4, (name, seed, err.max())


def _scene_with(poly, seed=0, height=3.0):
    sc = sample_room(seed, furniture=False)
    return dataclasses.replace(sc, polygon=np.asarray(poly, np.float64), height=height,
                               wall_material=np.full(len(poly), sc.wall_material[0]), decals=np.zeros((0, 7)),
                               decal_material=np.zeros(0, np.int64))


def _reference_boundary(cam, pose, sc):
    """Per column: v of the nearest projected wall-ceiling / wall-floor line sample (dense samples, cam.project)."""
    W = cam.width
    R, t = pose[:3, :3], pose[:3, 3]
    poly = sc.polygon
    s = np.linspace(0, 1, 20001)
    cols = np.arange(W) + 0.5
    best = np.full((2, W), np.nan)
    best_d = np.full((2, W), np.inf)
    for k in range(len(poly)):
        a, b = poly[k], poly[(k + 1) % len(poly)]
        xy = a + s[:, None] * (b - a)
        for j, z in ((0, sc.height), (1, 0.0)):
            pw = np.concatenate([xy, np.full((len(s), 1), z)], 1)
            pc = (pw - t) @ R
            uv, ok = cam.project(torch.as_tensor(pc))
            uv = uv.numpy()
            du = np.abs(uv[None, :, 0] - cols[:, None])
            du = np.minimum(du, W - du)
            i = du.argmin(1)
            close = du[np.arange(W), i] < 0.02
            dist = np.linalg.norm(pc[i], axis=1)
            take = close & (dist < best_d[j])
            best[j, take] = uv[i[take], 1]
            best_d[j, take] = dist[take]
    return best


ROOMS = {
    "box": [[-2.0, -1.5], [3.0, -1.5], [3.0, 2.5], [-2.0, 2.5]],
    "atlanta": [[-2.0, -1.5], [2.0, -1.5], [3.0, 0.0], [3.0, 2.5], [-2.0, 2.5]],
    "l_shape": [[-2.0, -1.5], [3.0, -1.5], [3.0, 1.0], [1.0, 1.0], [1.0, 3.0], [-2.0, 3.0]],
}


@pytest.mark.parametrize("name", list(CAMERAS))
@pytest.mark.parametrize("room", list(ROOMS))
def test_boundaries_match_projected_layout_lines(name, room):
    cam = build({**CAMERAS[name], "width": 256, "height": 128})
    sc = _scene_with(ROOMS[room])
    pose = np.eye(4)
    pose[:3, :3] = (rotation_z(torch.tensor(0.3, dtype=torch.float64)) @ upright_to_world(torch.float64)).numpy()
    pose[:3, 3] = (-0.4, 0.2, 1.4)
    out = render(sc, cam, pose)
    ref = _reference_boundary(cam, pose, sc)
    got = out["boundary"].numpy()
    assert out["boundary_valid"].all()
    assert np.isfinite(ref).all()
    err = np.abs(got - ref)
    assert err.max() < 0.02, err.max()   # acceptance: < 0.5 px; measured ~1e-3 px (reference sampling)
    assert np.median(err) < 0.05
    # corners project where the rendered corner columns are: visible corner u equals a wall-wall change
    uv = out["corners_uv"][: sc.num_walls].numpy()
    assert np.allclose(uv[:, 0, 0], uv[:, 1, 0], atol=1e-3)  # vertical edges project to one column


def test_layout_keys_and_conventions():
    cam = build(CAMERAS["noncentral_pano"])
    sc = sample_room(5)
    pose = place_camera(sc, cam, 5)
    out = render(sc, cam, pose)
    n = sc.num_walls
    assert out["num_walls"].item() == n
    assert torch.allclose(out["horizon_normal"], torch.tensor([0.0, -1.0, 0.0]), atol=1e-6)
    assert torch.allclose(out["rotation"], torch.eye(3), atol=1e-6)
    cw, cc = out["corners_world"][:n].double(), out["corners_cam"][:n].double()
    pose_t = torch.as_tensor(pose)
    assert torch.allclose(cc @ pose_t[:3, :3].T + pose_t[:3, 3], cw, atol=1e-5)
    assert (out["corners_world"][n:] == 0).all() and not out["corners_valid"][n:].any()
    # Plücker lines: unit direction, moment = point x direction for both end corners
    L = out["lines_cam"][:n].double()
    d, m = L[..., :3], L[..., 3:]
    assert torch.allclose(d.norm(dim=-1), torch.ones(n, 2, dtype=torch.float64), atol=1e-6)
    nxt = torch.roll(cc, -1, 0)
    assert torch.allclose(torch.linalg.cross(nxt, d, dim=-1), m, atol=1e-5)
    assert (out["corner_heat"] <= 1).all() and out["corner_heat"].max() > 0.95
    assert out["edges"].shape == (1, 64, 128) and out["edges"].sum() > 0
    # layout_seg: ceiling above the ceiling boundary, floor below the floor boundary
    ls = out["layout_seg"]
    v = torch.arange(64).double()[:, None] + 0.5
    b = out["boundary"].double()
    assert (ls[(v < b[0][None]).expand(64, 128)] == 1).all()
    assert (ls[(v > b[1][None]).expand(64, 128)] == 3).all()


def test_normals_are_unit_and_face_the_camera():
    cam = build(CAMERAS["equirect"])
    sc = sample_room(7)
    pose = place_camera(sc, cam, 7)
    out = render(sc, cam, pose, layout=False)
    n = out["normal"].reshape(3, -1).T.double()
    assert torch.allclose(n.norm(dim=-1), torch.ones(len(n), dtype=torch.float64), atol=1e-5)
    d = cam.unproject_grid(torch.float64).direction.reshape(-1, 3)
    assert ((n * d).sum(-1) <= 1e-6).all()
    sem = out["semantic"].reshape(-1)
    # floors look up (world +z = camera -y for an upright camera), ceilings down
    assert torch.allclose(n[sem == CLASS_ID["floor"]], torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64), atol=1e-5)
    assert torch.allclose(n[sem == CLASS_ID["ceiling"]], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), atol=1e-5)
    img = out["image"]
    assert img.dtype == torch.float32 and img.min() >= 0 and img.max() <= 1 and torch.isfinite(img).all()


@pytest.mark.parametrize("cfg", [
    {"type": "pinhole", "width": 64, "height": 48, "fx": 40.0, "fy": 40.0, "cx": 32.0, "cy": 24.0},
    "fisheye_equiangular",
])
def test_any_camera_renders_with_invalid_pixels_zeroed(cfg):
    from omnidl.cameras import resolve_camera
    cam = resolve_camera(cfg, 64, 64) if isinstance(cfg, str) else build(cfg)
    sc = sample_room(11)
    pose = place_camera(sc, cam, 11, rotation="random")
    out = render(sc, cam, pose)
    valid = out["valid"]
    rays = cam.unproject_grid(torch.float64)
    assert torch.equal(valid, rays.valid & (out["depth"][0] > 0))
    assert (out["depth"][0][~valid] == 0).all() and (out["semantic"][~valid] == 0).all()
    assert (out["depth"][0][valid] > 0).all()
    # horizon normal = world up in the camera frame; rotation maps it to the upright camera's up (-y)
    up = out["rotation"].double() @ out["horizon_normal"].double()
    assert torch.allclose(up, torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64), atol=1e-5)
    assert torch.allclose(out["horizon_normal"].double(),
                          torch.as_tensor(pose[:3, :3].T @ np.array([0, 0, 1.0])), atol=1e-6)


def test_noncentral_rig_circle_is_free():
    from shapely.geometry import Point, Polygon
    cam = build({"type": "noncentral_pano", "width": 64, "height": 32, "rc": 1.0})
    for seed in range(10):
        sc = sample_room(seed)
        try:
            pose = place_camera(sc, cam, seed)
        except RuntimeError:
            continue
        circle = Point(*pose[:2, 3]).buffer(1.0)
        assert Polygon(sc.polygon).contains(circle)
        for fp in sc.footprints:
            assert not Polygon(fp).intersects(circle)
        assert 1.0 < pose[2, 3] < sc.height - 1.0


def test_same_inputs_give_bit_identical_renders():
    cam = build(CAMERAS["noncentral_pano"])
    sc = sample_room(3)
    pose = place_camera(sc, cam, 3)
    a, b = render(sc, cam, pose), render(sample_room(3), cam, place_camera(sample_room(3), cam, 3))
    for k in a:
        if k != "meta":
            assert torch.equal(a[k], b[k]), k


def _config_cameras():
    from omnidl.cameras import CAMERA_CONFIG_DIR
    return sorted(p.stem for p in CAMERA_CONFIG_DIR.glob("*.yaml"))


@pytest.mark.parametrize("name", _config_cameras())
def test_every_configured_camera_renders_consistent_depth(name):
    from shapely.geometry import Point, Polygon
    from omnidl.cameras import resolve_camera
    cam = resolve_camera(name, 32, 32)
    sc = sample_room(4)
    pose = place_camera(sc, cam, 4)
    out = render(sc, cam, pose)
    valid = out["valid"].numpy().reshape(-1)
    assert valid.mean() > 0.3
    rays = cam.unproject_grid(dtype=torch.float64)
    assert np.array_equal(valid, rays.valid.numpy().reshape(-1))
    pts = rays.at(out["depth"][0].double()).reshape(-1, 3).numpy() @ pose[:3, :3].T + pose[:3, 3]
    pts = pts[valid]
    assert pts[:, 2].min() > -1e-4 and pts[:, 2].max() < sc.height + 1e-4
    room = Polygon(sc.polygon).buffer(1e-4)
    assert all(room.contains(Point(p[:2])) for p in pts)


def test_edge_map_reads_back_as_the_boundaries():
    """scaledLayout's reading of EM_gt: first edge pixel from the top (upper half) / from the bottom (lower half)."""
    cam = build({"type": "noncentral_pano", "width": 128, "height": 64, "rc": 0.5})
    sc = sample_room(9)
    out = render(sc, cam, place_camera(sc, cam, 9))
    em = out["edges"][0].numpy() > 0
    H = em.shape[0]
    b, ok = out["boundary"].numpy(), out["boundary_valid"].numpy()
    top = em[: H // 2].argmax(0)
    bottom = H - 1 - em[::-1][: H // 2].argmax(0)
    assert ok.all()
    assert np.array_equal(top, np.floor(b[0]).astype(int))
    assert np.array_equal(bottom, np.floor(b[1]).astype(int))


def test_shadows_only_darken():
    cam = build(CAMERAS["equirect"])
    sc = sample_room(42)
    pose = place_camera(sc, cam, 42)
    lit, shadowed = render(sc, cam, pose, layout=False), render(sc, cam, pose, layout=False, shadows=True)
    assert torch.equal(lit["depth"], shadowed["depth"]) and torch.equal(lit["semantic"], shadowed["semantic"])
    assert (shadowed["image"] <= lit["image"] + 1e-6).all() and (shadowed["image"] < lit["image"] - 1e-3).any()


def test_render_is_independent_of_the_thread_policy(monkeypatch):
    """render(threads=...) only changes how many intra-op threads run, never the result (bitwise)."""
    from omnidl.utils import threads as T
    cam = build({"type": "equirect", "width": 64, "height": 32})
    sc = sample_room(3)
    pose = place_camera(sc, cam, 3)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        ref = render(sc, cam, pose, threads=None)
        seen = []
        monkeypatch.setattr(T, "runnable_tasks", lambda: 10 ** 6)  # oversubscribed: auto -> 1 thread
        orig = T.limit_threads

        def spy(n):
            seen.append(T.auto_threads() if n == "auto" else n)
            return orig(n)
        import sys
        monkeypatch.setattr(sys.modules["omnidl.synth.render"], "limit_threads", spy)
        for threads in ("auto", 1, 2):
            out = render(sc, cam, pose, threads=threads)
            for k, v in ref.items():
                if isinstance(v, torch.Tensor):
                    assert torch.equal(out[k], v), k
        assert seen == [1, 1, 2]
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
