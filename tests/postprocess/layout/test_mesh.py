"""A layout as a textured mesh: closed, facing into the room, with the texture coordinates the panorama's own
mapping gives (checked with the documented equirectangular formula, not the camera code), cut at the seam and
the poles, and saved as glTF binary / OBJ without replacing files."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from omnidl.cameras import Equirectangular, NonCentralPanorama
from omnidl.geometry.rotations import UPRIGHT_TO_WORLD
from omnidl.postprocess.layout import Layout
from omnidl.postprocess.layout.mesh import POLE_TOL, layout_mesh, room_mesh, save_layout_mesh
from omnidl.viz.mesh import glb_accessor, read_glb

W, H = 256, 128
SQUARE = np.array([[2.0, 1.5], [-1.2, 2.5], [-2.0, -1.0], [1.5, -2.2]])
L_ROOM = np.array([[3, -1], [3, 2], [1, 2], [1, 0.5], [-1, 0.5], [-1, -1]], float)   # corners hidden from the camera
Y_UP = np.diag([1.0, -1.0, -1.0])


def room(poly, h_f=-1.6, h_c=1.2):
    return np.c_[poly, np.full(len(poly), h_f)], np.c_[poly, np.full(len(poly), h_c)]


def periodic_panorama(w=W, h=H) -> np.ndarray:
    """RGB colours that are smooth functions of longitude/latitude (the same at u = 0 and u = 1)."""
    lon = (np.arange(w) + 0.5) / w * 2 * np.pi - np.pi
    lat = np.pi / 2 - (np.arange(h) + 0.5) / h * np.pi
    lo, la = np.meshgrid(lon, lat)
    return np.stack([127.5 + 120 * np.cos(lo), 127.5 + 120 * np.sin(lo), 127.5 + 120 * np.sin(la)],
                    -1).round().astype(np.uint8)


def camera_frame(p_yup: np.ndarray, R=None) -> np.ndarray:
    """y-up frame -> camera frame: inverse of ``diag(1, -1, -1) @ R_up_cam`` (docs of omnidl.viz.ply)."""
    M = Y_UP @ (np.eye(3) if R is None else np.asarray(R))
    return p_yup @ M


def lonlat_uv(pc: np.ndarray) -> np.ndarray:
    """docs/design.md: λ = atan2(x, z), φ = atan2(-y, hypot(x, z)); u = (λ + π) / 2π, v = (π/2 − φ) / π."""
    lon = np.arctan2(pc[:, 0], pc[:, 2])
    lat = np.arctan2(-pc[:, 1], np.hypot(pc[:, 0], pc[:, 2]))
    return np.stack([(lon + np.pi) / (2 * np.pi), (np.pi / 2 - lat) / np.pi], 1)


def pole_mask(pc: np.ndarray) -> np.ndarray:
    return np.hypot(pc[:, 0], pc[:, 2]) <= POLE_TOL * np.linalg.norm(pc, axis=1)


def merged_edges(mesh) -> np.ndarray:
    """How many faces use each edge once vertices at the same place are merged (seam and pole copies of a vertex
    are bit-identical)."""
    _, inv = np.unique(mesh.positions, axis=0, return_inverse=True)
    f = inv.reshape(-1)[mesh.faces]
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), 1)
    return np.unique(e, axis=0, return_counts=True)[1]


def normals(mesh):
    P, F = mesh.positions, mesh.faces
    a, b, c = P[F[:, 0]], P[F[:, 1]], P[F[:, 2]]
    return np.cross(b - a, c - a), (a + b + c) / 3


def check_uv(mesh, R=None, tol=1e-9):
    """Every vertex has the panorama's own texture coordinate (pole vertices: the top/bottom row); no triangle
    spans the seam."""
    pc = camera_frame(mesh.positions, R)
    want = lonlat_uv(pc)
    pole = pole_mask(pc)
    du = np.abs((mesh.uv[:, 0] - want[:, 0] + 0.5) % 1 - 0.5)
    dv = np.abs(mesh.uv[:, 1] - want[:, 1])
    assert du[~pole].max() < tol and dv[~pole].max() < tol and dv[pole].max(initial=0) < POLE_TOL
    assert ((mesh.uv[:, 0] >= 0) & (mesh.uv[:, 0] <= 1)).all()
    spread = mesh.uv[mesh.faces, 0].max(1) - mesh.uv[mesh.faces, 0].min(1)
    assert spread.max() < 0.5


def test_star_room_is_closed_inward_and_textured_exactly():
    mesh = room_mesh(*room(SQUARE), periodic_panorama())
    assert [g[0] for g in mesh.groups] == ["floor", "ceiling", "walls"] and mesh.info["star_shaped"]
    assert set(merged_edges(mesh)) == {2}                                # closed: no crack anywhere
    n, centre = normals(mesh)
    assert ((n * -centre).sum(1) > 0).all()                              # every face seen from the camera: inside
    check_uv(mesh)
    # the area is the room's: floor + ceiling + walls
    floor_area = 0.5 * abs(np.sum(SQUARE[:, 0] * np.roll(SQUARE[:, 1], -1) - np.roll(SQUARE[:, 0], -1) * SQUARE[:, 1]))
    walls = np.linalg.norm(np.roll(SQUARE, -1, 0) - SQUARE, axis=1).sum() * 2.8
    area = 0.5 * np.linalg.norm(n, axis=1).sum()
    assert area == pytest.approx(2 * floor_area + walls, rel=1e-9)
    # y-up frame: the floor is at y = -1.6, the ceiling at +1.2, as the point clouds
    np.testing.assert_allclose(mesh.positions[np.unique(mesh.group("floor"))][:, 1], -1.6)
    np.testing.assert_allclose(mesh.positions[np.unique(mesh.group("ceiling"))][:, 1], 1.2)


def test_seam_vertices_are_doubled_with_u_0_and_1():
    mesh = room_mesh(*room(SQUARE), periodic_panorama(), step_deg=4)
    pc = camera_frame(mesh.positions)
    on_seam = (np.abs(pc[:, 0]) < 1e-9) & (pc[:, 2] < 0) & ~pole_mask(pc)
    at0 = {tuple(np.round(p, 6)) for p in mesh.positions[on_seam & (mesh.uv[:, 0] == 0)]}
    at1 = {tuple(np.round(p, 6)) for p in mesh.positions[on_seam & (mesh.uv[:, 0] == 1)]}
    assert len(at0) > 10 and at0 == at1                                  # the same points, once per side
    # every triangle touching the seam lies on one side of it
    x = pc[mesh.faces, 0]
    assert not ((x > 1e-9).any(1) & (x < -1e-9).any(1) & (pc[mesh.faces, 2] < 0).all(1)).any()


def test_texture_is_within_a_fraction_of_a_pixel_inside_triangles():
    """Linear interpolation across a triangle vs the panorama's mapping of the point (angle, in pixels at the
    equator of a 1024-column panorama), at random points of every triangle."""
    mesh = room_mesh(*room(SQUARE), np.zeros((512, 1024, 3), np.uint8))
    F = mesh.faces
    w = np.random.default_rng(0).dirichlet([1, 1, 1], size=len(F))[..., None]
    X = camera_frame((w * mesh.positions[F]).sum(1))
    X /= np.linalg.norm(X, axis=1, keepdims=True)
    uv = (w * mesh.uv[F]).sum(1)
    lon, lat = uv[:, 0] * 2 * np.pi - np.pi, np.pi / 2 - uv[:, 1] * np.pi
    d = np.stack([np.cos(lat) * np.sin(lon), -np.sin(lat), np.cos(lat) * np.cos(lon)], 1)
    err = np.arccos(np.clip((d * X).sum(1), -1, 1)) * 1024 / (2 * np.pi)
    assert err.max() < 0.5, err.max()


def test_tilted_camera_is_cut_at_its_own_seam_and_pole():
    c, s = math.cos(0.12), math.sin(0.12)
    R = np.array([[1, 0, 0], [0, c, -s], [0, s, c]]) @ np.array([[math.cos(0.08), -math.sin(0.08), 0],
                                                                  [math.sin(0.08), math.cos(0.08), 0], [0, 0, 1]])
    mesh = room_mesh(*room(SQUARE), periodic_panorama(), R_up_cam=R, step_deg=4)
    assert set(merged_edges(mesh)) == {2}
    check_uv(mesh, R)
    pc = camera_frame(mesh.positions, R)
    assert pole_mask(pc).sum() >= 2                                     # the camera's zenith and nadir are vertices
    np.testing.assert_allclose(mesh.positions[np.unique(mesh.group("floor"))][:, 1], -1.6, atol=1e-12)


def test_room_not_star_shaped_from_the_camera():
    mesh = room_mesh(*room(L_ROOM), periodic_panorama(), step_deg=4)
    assert not mesh.info["star_shaped"]
    check_uv(mesh)
    n, centre = normals(mesh)
    F = mesh.faces
    fl, ce = mesh.group("floor"), mesh.group("ceiling")
    assert (n[: len(fl), 1] > 0).all() and (n[len(fl): len(fl) + len(ce), 1] < 0).all()
    # walls face into the room: a step along the normal from a wall's centre stays inside the polygon
    from matplotlib.path import Path as MPath
    walls = slice(len(fl) + len(ce), len(F))
    step = centre[walls] + 1e-3 * n[walls] / np.linalg.norm(n[walls], axis=1, keepdims=True)
    top = np.c_[step[:, 0], -step[:, 2]]                                # y-up (x, -z) is the layout (x, y)
    assert MPath(L_ROOM).contains_points(top).all()


def test_noncentral_panorama_uses_its_own_projection():
    cam = NonCentralPanorama(W, H, rc=0.3)
    mesh = room_mesh(*room(SQUARE), periodic_panorama(), camera=cam, step_deg=4)
    pc = camera_frame(mesh.positions)
    rho = np.hypot(pc[:, 0], pc[:, 2])
    seen = rho > 0.3 + 1e-6
    lon, lat = np.arctan2(pc[:, 0], pc[:, 2]), np.arctan2(-pc[:, 1], rho - 0.3)      # its Eq. 2.14
    want = np.stack([(lon + np.pi) / (2 * np.pi), (np.pi / 2 - lat) / np.pi], 1)
    du = np.abs((mesh.uv[:, 0] - want[:, 0] + 0.5) % 1 - 0.5)
    assert du[seen].max() < 1e-9 and np.abs(mesh.uv[seen, 1] - want[seen, 1]).max() < 1e-9
    assert set(merged_edges(mesh)) == {2}


def test_layout_object_dict_and_files(tmp_path):
    lay = Layout(ok=True, corners=SQUARE, h_ceiling=1.2, h_floor=-1.6)
    tex = torch.rand(3, H, W)
    a, b = layout_mesh(lay, tex, step_deg=8), layout_mesh(lay.to_dict(), tex, step_deg=8)
    np.testing.assert_array_equal(a.positions, b.positions)
    assert a.texture.shape == (H, W, 3) and a.texture.dtype == np.uint8
    [glb] = save_layout_mesh(lay, tex, tmp_path / "room.glb", step_deg=8)
    doc, binary = read_glb(glb)
    assert [m["name"] for m in doc["meshes"]] == ["floor", "ceiling", "walls"]
    uv = glb_accessor(doc, binary, doc["meshes"][2]["primitives"][0]["attributes"]["TEXCOORD_0"])
    assert uv.min() >= 0 and uv.max() <= 1
    files = save_layout_mesh({"layout": lay.to_dict()}, tex, tmp_path / "room.obj", step_deg=8)
    assert [f.name for f in files] == ["room.obj", "room.mtl", "room_texture.png"]
    with pytest.raises(FileExistsError, match="already exists"):
        save_layout_mesh(lay, tex, tmp_path / "room.glb")
    with pytest.raises(ValueError, match=r"should end in one of \['.glb', '.obj'\]"):
        save_layout_mesh(lay, tex, tmp_path / "room.ply")
    with pytest.raises(ValueError, match="no layout to mesh .*too few corners"):
        layout_mesh(Layout.failed("too few corners"), tex)


@pytest.mark.parametrize("kwargs, match", [
    ({"floor": room(SQUARE, h_f=0.5)[0]}, "camera must be between floor and ceiling"),
    ({"floor": room(SQUARE)[0][:3]}, "differ in shape"),
    ({"floor": np.full((4, 3), np.nan)}, "non-finite"),
    ({"camera": Equirectangular(W, H, lon_min=-1.0, lon_max=1.0)}, "not a full 360"),
    ({"camera": Equirectangular(2 * W, H)}, "camera is 512x128 but the panorama is 256x128"),
    ({"image": np.zeros((H, W), np.uint8)}, "panorama must be"),
    ({"R_up_cam": np.eye(3) * 2}, "must be a .3, 3. rotation"),
    ({"floor": room(np.array([[1, 0], [2, 0], [3, 0]]))[0], "ceiling": room(np.array([[1, 0], [2, 0], [3, 0]]))[1]},
     "has no area"),
])
def test_bad_inputs_are_named(kwargs, match):
    fl, ce = room(SQUARE)
    args = {"floor": fl, "ceiling": ce, "image": periodic_panorama(), **kwargs}
    with pytest.raises(ValueError, match=match):
        room_mesh(args.pop("floor"), args.pop("ceiling"), args.pop("image"), **args)


def test_trimesh_samples_the_panorama_at_each_vertex(tmp_path):
    """An independent reader (trimesh: its glTF/OBJ import and texture sampling) sees at every vertex the colour the
    panorama has in that vertex's direction."""
    trimesh = pytest.importorskip("trimesh")
    lay = Layout(ok=True, corners=SQUARE, h_ceiling=1.2, h_floor=-1.6)
    tex = periodic_panorama()
    files = save_layout_mesh(lay, tex, tmp_path / "room.glb", step_deg=6) + \
        save_layout_mesh(lay, tex, tmp_path / "room.obj", step_deg=6)
    for path in (files[0], files[1]):
        loaded = trimesh.load(path)
        geoms = list(loaded.geometry.values()) if hasattr(loaded, "geometry") else [loaded]
        for g in geoms:
            col = g.visual.to_color().vertex_colors[:, :3].astype(float)
            pc = camera_frame(np.asarray(g.vertices, float))
            keep = ~(np.hypot(pc[:, 0], pc[:, 2]) < 1e-6)                # pole vertices: any longitude
            lon, lat = np.arctan2(pc[:, 0], pc[:, 2]), np.arctan2(-pc[:, 1], np.hypot(pc[:, 0], pc[:, 2]))
            want = np.stack([127.5 + 120 * np.cos(lon), 127.5 + 120 * np.sin(lon), 127.5 + 120 * np.sin(lat)], -1)
            assert np.abs(col - want)[keep].max() < 6, (path.name, np.abs(col - want)[keep].max())


@settings(max_examples=12, deadline=None, derandomize=True)
@given(n=st.integers(3, 7), seed=st.integers(0, 10_000), tilt=st.floats(0.0, 0.2), yaw=st.floats(-math.pi, math.pi))
def test_any_star_room_any_tilt_closed_and_exact(n, seed, tilt, yaw):
    rng = np.random.default_rng(seed)
    ang = np.sort(rng.uniform(-math.pi, math.pi, n)) + yaw
    if np.max(np.diff(np.r_[ang, ang[0] + 2 * math.pi])) >= math.pi - 0.05:
        ang = yaw + np.linspace(-math.pi, math.pi, n, endpoint=False)    # keep the camera inside
    r = rng.uniform(0.8, 6.0, n)
    poly = np.c_[r * np.cos(ang), r * np.sin(ang)]
    ax = rng.normal(size=3)
    ax /= np.linalg.norm(ax)
    R = torch.linalg.matrix_exp(torch.tensor(np.cross(np.eye(3), ax * tilt))).numpy()
    mesh = room_mesh(*room(poly, -rng.uniform(0.5, 2.0), rng.uniform(0.3, 2.0)), periodic_panorama(64, 32),
                     R_up_cam=R, step_deg=6.0)
    assert set(merged_edges(mesh)) == {2}
    check_uv(mesh, R, tol=1e-8)


def test_layout_frame_matches_the_predict_command():
    """The mesh frame is the PLYs' gravity-aligned y-up frame: layout (x, y, z) -> (x, z, -y)."""
    U = np.asarray(UPRIGHT_TO_WORLD)
    np.testing.assert_allclose(Y_UP @ U.T @ [1.0, 2.0, 3.0], [1.0, 3.0, -2.0])
    mesh = room_mesh(*room(SQUARE), periodic_panorama(), step_deg=10)
    corner = np.array([2.0, -1.6, -1.5])                                 # layout (2, 1.5, -1.6)
    assert np.isclose(mesh.positions, corner).all(1).any()
