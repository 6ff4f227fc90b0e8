"""COLMAP cameras.txt/.bin: every model against pycolmap (dev-only oracle), bit-exact round trips."""
import math
import struct

import numpy as np
import pytest
import torch

from omnidl.cameras import list_cameras
from omnidl.cameras.io import UnsupportedModelError, colmap, load, load_all, save

pycolmap = pytest.importorskip("pycolmap")

W, H = 640, 480
#: (COLMAP model, params, omnidl family) — params in COLMAP's order (models.h)
CASES = [
    ("SIMPLE_PINHOLE", [300.0, 320.5, 240.25], "pinhole"),
    ("PINHOLE", [300.0, 310.0, 320.5, 240.25], "pinhole"),
    ("SIMPLE_RADIAL", [300.0, 320.5, 240.25, -0.05], "opencv"),
    ("RADIAL", [300.0, 320.5, 240.25, -0.05, 0.01], "opencv"),
    ("OPENCV", [300.0, 310.0, 320.5, 240.25, -0.05, 0.01, 0.001, -0.002], "opencv"),
    ("FULL_OPENCV", [300.0, 310.0, 320.5, 240.25, -0.05, 0.01, 0.001, -0.002, 0.001, 0.02, -0.003, 0.0005],
     "opencv"),
    ("OPENCV_FISHEYE", [200.0, 205.0, 320.5, 240.25, 0.05, -0.01, 0.002, -1e-4], "kannala_brandt"),
    ("FOV", [200.0, 205.0, 320.5, 240.25, 0.9], "fov"),
    ("SIMPLE_RADIAL_FISHEYE", [200.0, 320.5, 240.25, 0.05], "kannala_brandt"),
    ("RADIAL_FISHEYE", [200.0, 320.5, 240.25, 0.05, -0.01], "kannala_brandt"),
    ("THIN_PRISM_FISHEYE", [200.0, 205.0, 320.5, 240.25, 0.05, -0.01, 0.0, 0.0, 0.002, -1e-4, 0.0, 0.0],
     "kannala_brandt"),
    ("THIN_PRISM_FISHEYE", [200.0, 205.0, 320.5, 240.25, 0.0, 0.0, 0.001, -0.0015, 0.0, 0.0, 0.002, -0.001],
     "fisheye624"),
    ("RAD_TAN_THIN_PRISM_FISHEYE", [200.0, 205.0, 320.5, 240.25, 0.05, -0.01, 0.002, -1e-4, 1e-5, -1e-6, 0.001,
                                    -0.0015, 0.002, -0.0003, -0.001, 0.0002], "fisheye624"),
    ("SIMPLE_FISHEYE", [200.0, 320.5, 240.25], "kannala_brandt"),
    ("FISHEYE", [200.0, 205.0, 320.5, 240.25], "kannala_brandt"),
    ("SIMPLE_DIVISION", [200.0, 320.5, 240.25, -0.1], "scaramuzza"),
    ("DIVISION", [200.0, 205.0, 320.5, 240.25, -0.1], "scaramuzza"),
    ("DIVISION", [200.0, 205.0, 320.5, 240.25, 0.02], "scaramuzza"),
    ("EUCM", [200.0, 205.0, 320.5, 240.25, 0.6, 1.1], "eucm"),
    ("EQUIRECTANGULAR", [float(W), float(H)], "equirect"),
]
IDS = [f"{m}-{fam}" for m, _, fam in CASES]


def _available(model, family):
    if model not in pycolmap.CameraModelId.__members__:
        pytest.skip(f"COLMAP model {model} is not in the installed pycolmap {pycolmap.__version__}")
    if family not in list_cameras():
        pytest.skip(f"omnidl family {family!r} (for COLMAP {model}) is not registered yet")


def _pycolmap_camera(model, params):
    cam = pycolmap.Camera.create_from_model_name(1, model, 100.0, W, H)
    cam.params = np.asarray(params, dtype=np.float64)
    return cam


def _points(n, theta_max, seed, behind=False):
    g = np.random.default_rng(seed)
    theta = theta_max * np.sqrt(g.random(n))
    psi = g.uniform(-np.pi, np.pi, n)
    d = np.stack([np.sin(theta) * np.cos(psi), np.sin(theta) * np.sin(psi), np.cos(theta)], -1)
    return d * g.uniform(0.5, 5.0, (n, 1))


def _write_txt(path, rows):
    lines = ["# Camera list with one line of data per camera:"]
    lines += [" ".join([str(cid), model, str(W), str(H)] + [repr(float(v)) for v in params]) for cid, model, params
              in rows]
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("model,params,family", CASES, ids=IDS)
def test_every_model_agrees_with_pycolmap(tmp_path, model, params, family):
    _available(model, family)
    path = tmp_path / "cameras.txt"
    _write_txt(path, [(1, model, params)])
    cam = load(path)
    assert type(cam).name == family
    ref = _pycolmap_camera(model, params)
    # (Scaramuzza = division models: omnidl projects up to the image corners' angle, 73 deg here)
    theta_max = math.radians(60 if family in ("pinhole", "opencv", "scaramuzza") else 85)
    pts = _points(2000, theta_max, 0)
    uv_ref = ref.img_from_cam(pts)
    uv, _ = cam.project(torch.from_numpy(pts))
    ok = np.isfinite(uv_ref).all(-1)
    assert ok.mean() > 0.9
    err = np.abs(uv.numpy()[ok] - uv_ref[ok]).max()
    assert err < 1e-6, f"{model}: max |uv - pycolmap| = {err:.3g} px"
    # rays of pixels inside the image agree too
    pix = uv.numpy()[ok]
    inside = (pix[:, 0] > 1) & (pix[:, 0] < W - 1) & (pix[:, 1] > 1) & (pix[:, 1] < H - 1)
    rays = cam.unproject(torch.from_numpy(pix[inside]))
    d_ref = ref.cam_ray_from_img(pix[inside])
    d_ref /= np.linalg.norm(d_ref, axis=-1, keepdims=True)
    assert rays.valid.all()
    assert np.abs(rays.direction.numpy() - d_ref).max() < 1e-7


def test_thin_prism_fisheye_with_radial_and_prism_terms_is_refused(tmp_path):
    path = tmp_path / "cameras.txt"
    _write_txt(path, [(1, "THIN_PRISM_FISHEYE",
                       [200.0, 205.0, 320.5, 240.25, 0.05, -0.01, 0.001, 0.0, 0.0, 0.0, 0.0, 0.0])])
    with pytest.raises(UnsupportedModelError, match="THIN_PRISM_FISHEYE"):
        load(path)


def test_spherical_is_not_a_colmap_model(tmp_path):
    # COLMAP 4.1.1 (models.h) and pycolmap 4.2.1 have no SPHERICAL model: the spherical one is EQUIRECTANGULAR
    assert "SPHERICAL" not in pycolmap.CameraModelId.__members__
    path = tmp_path / "cameras.txt"
    _write_txt(path, [(1, "SPHERICAL", [float(W), float(H)])])
    with pytest.raises(UnsupportedModelError, match=r"no camera model 'SPHERICAL'.*EQUIRECTANGULAR"):
        load(path)


#: DIVISION rows: COLMAP's text layout (docs "Output Format", cameras.txt), params "fx, fy, cx, cy, k"
DIVISION_TXT = """# Camera list with one line of data per camera:
#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]
# Number of cameras: 2
1 SIMPLE_DIVISION 640 480 250.5 320.25 239.75 -0.2
2 DIVISION 640 480 250.5 251.25 320.25 239.75 -0.2
"""


def test_division_models_read_as_scaramuzza_and_round_trip(tmp_path):
    from omnidl.cameras import Scaramuzza
    path = tmp_path / "cameras.txt"
    path.write_text(DIVISION_TXT)
    cams = load_all(path)
    assert all(isinstance(c, Scaramuzza) for c in cams.values())
    assert cams[1].pol == (-250.5, 0.0, 0.2 / 250.5) and cams[1].c == 1.0
    assert (cams[1].cx, cams[1].cy) == (320.25, 239.75)
    assert cams[2].c == 251.25 / 250.5
    out = save(cams, tmp_path / "out_cameras.txt", format="colmap")
    rows = [ln.split() for ln in out.read_text().splitlines() if not ln.startswith("#")]
    assert [r[1] for r in rows] == ["SIMPLE_DIVISION", "DIVISION"]
    for row, ref in zip(rows, [[250.5, 320.25, 239.75, -0.2], [250.5, 251.25, 320.25, 239.75, -0.2]]):
        assert np.allclose([float(t) for t in row[4:]], ref, rtol=1e-15, atol=0)
    back = load_all(out)
    pts = torch.from_numpy(_points(3000, math.radians(100), 4))
    for cid in cams:
        uv0, ok0 = cams[cid].project(pts)
        uv1, ok1 = back[cid].project(pts)
        assert torch.equal(ok0, ok1) and (uv0 - uv1)[ok0].abs().max() < 1e-9
    # a Scaramuzza camera that is not of the division form is refused, naming why
    from omnidl.cameras import Scaramuzza as S
    with pytest.raises(UnsupportedModelError, match=r"'colmap'.*division model .*pol = "):
        save(S.example(), tmp_path / "s.txt", format="colmap")


def _canonical_rows():
    """One camera per available model, with parameters the writer keeps in the same COLMAP model."""
    rows, families = [], set(list_cameras())
    for i, (model, params, family) in enumerate(CASES):
        # (division models are held as Scaramuzza ratios: round trips to rounding, tested on their own)
        if family in families and model not in ("THIN_PRISM_FISHEYE", "SIMPLE_FISHEYE", "FISHEYE", "SIMPLE_DIVISION",
                                                "DIVISION"):
            rows.append((i + 1, model, params))
    return rows


def test_cameras_txt_round_trips_bit_exactly(tmp_path):
    rows = _canonical_rows()
    src = tmp_path / "src" / "cameras.txt"
    src.parent.mkdir()
    # awkward floats: repr round trips them exactly
    rows = [(cid, m, [p * (1 + 1e-13 * k) if k >= 4 else p for k, p in enumerate(params)]) for cid, m, params in rows]
    _write_txt(src, rows)
    cams = load_all(src)
    assert list(cams) == [cid for cid, _, _ in rows]
    out = save(cams, tmp_path / "cameras.txt")
    again = load_all(out)
    assert again == cams
    data = [ln.split() for ln in out.read_text().splitlines() if not ln.startswith("#")]
    for (cid, model, params), tok in zip(rows, data):
        assert tok[:4] == [str(cid), model, str(W), str(H)]
        assert [float(t) for t in tok[4:]] == params  # bit-exact values, same model
    # and the text itself is a fixed point
    assert save(again, tmp_path / "c2.txt", format="colmap").read_text() == out.read_text()


def test_cameras_bin_layout_and_round_trip(tmp_path):
    rows = _canonical_rows()
    src = tmp_path / "cameras.txt"
    _write_txt(src, rows)
    cams = load_all(src)
    out = save(cams, tmp_path / "cameras.bin")
    blob = out.read_bytes()
    # documented layout: uint64 n; per camera int32 id, int32 model id, uint64 w, uint64 h, float64 params[]
    (n,) = struct.unpack_from("<Q", blob, 0)
    assert n == len(rows)
    off = 8
    for cid, model, params in rows:
        assert struct.unpack_from("<iiQQ", blob, off) == (cid, colmap.MODEL_IDS[model], W, H)
        off += 24
        assert list(struct.unpack_from(f"<{len(params)}d", blob, off)) == params
        off += 8 * len(params)
    assert off == len(blob)
    assert load_all(out) == cams
    assert save(load_all(out), tmp_path / "again.bin").read_bytes() == blob


@pytest.mark.parametrize("binary", [False, True])
def test_files_agree_with_pycolmap_reconstruction_io(tmp_path, binary):
    rows = [r for r in _canonical_rows() if r[1] in pycolmap.CameraModelId.__members__]
    rec = pycolmap.Reconstruction()
    for cid, model, params in rows:
        cam = _pycolmap_camera(model, params)
        cam.camera_id = cid
        rec.add_camera(cam)
    ref_dir = tmp_path / "ref"
    ref_dir.mkdir()
    (rec.write_binary if binary else rec.write_text)(str(ref_dir))
    name = "cameras.bin" if binary else "cameras.txt"
    ours = load_all(ref_dir / name)  # COLMAP's file -> omnidl
    assert sorted(ours) == sorted(cid for cid, _, _ in rows)
    save(ours, ref_dir / name)  # omnidl's file -> COLMAP
    back = pycolmap.Reconstruction(str(ref_dir))
    for cid, model, params in rows:
        assert back.cameras[cid].model.name == model
        assert back.cameras[cid].params.tolist() == params
        assert (back.cameras[cid].width, back.cameras[cid].height) == (W, H)


def test_selector_errors_and_unsupported_writes(tmp_path):
    path = tmp_path / "cameras.txt"
    _write_txt(path, [(3, "PINHOLE", [300.0, 310.0, 320.5, 240.25]), (7, "SIMPLE_PINHOLE", [250.0, 320.0, 240.0])])
    assert load(path).fx == 300.0
    assert load(path, camera=7).fx == 250.0
    with pytest.raises(KeyError, match=r"\[3, 7\]"):
        load(path, camera=5)
    from omnidl.cameras import Unified
    with pytest.raises(UnsupportedModelError, match="'colmap'.*'unified'"):
        save(Unified.example(), tmp_path / "u.txt", format="colmap")
    bad = tmp_path / "bad.txt"
    bad.write_text("1 PINHOLE 640 480 300 310 320\n")
    with pytest.raises(ValueError, match=r"line 1.*PINHOLE needs 4 parameters"):
        load(bad)
