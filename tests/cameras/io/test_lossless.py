"""Interchange writers are lossless or refuse (issue 48 item 2): every registered camera x every writer format.

A camera saved to a format either comes back seeing exactly what it saw (same pixels and validity mask for a
dense grid of directions, same unprojection validity over the image) or ``save`` raises
``UnsupportedModelError`` naming the format and the family, and writes nothing. The status of every pair is
pinned in ``ROUND_TRIPS`` (the table of the issue note), so a writer that starts refusing, or starts
accepting, shows up here.
"""
import math
import warnings

import pytest
import torch

from omnidl.cameras import KannalaBrandt, Pinhole, get_camera_class, list_cameras
from omnidl.cameras.base import ResizedCamera
from omnidl.cameras import io
from omnidl.cameras.io import UnsupportedModelError, load, save

#: (id, file name, format) of every writer; ``woodscape`` is read-only (always refused)
WRITERS = [("colmap-txt", "cameras.txt", "colmap"), ("colmap-bin", "cameras.bin", "colmap"),
           ("kalibr", "camchain.yaml", "kalibr"), ("opencv-yaml", "calib.yaml", "opencv"),
           ("opencv-xml", "calib.xml", "opencv"), ("orbslam3", "orb.yaml", "orbslam3"),
           ("ocamcalib", "calib_results.txt", "ocamcalib"), ("kb_txt", "kb.txt", "kb_txt"),
           ("omnidl", "cam.yaml", "omnidl"), ("woodscape", "w.json", "woodscape")]

CAMERAS = {f"{name}-{i}": cam for name in list_cameras() for i, cam in enumerate(get_camera_class(name).examples())}
CAMERAS["resized-0"] = ResizedCamera.example()

COLMAP, KALIBR, OPENCV = {"colmap-txt", "colmap-bin"}, {"kalibr"}, {"opencv-yaml", "opencv-xml"}
#: which writers round-trip each registry example (every other writer must refuse it)
ROUND_TRIPS = {
    "catadioptric-0": {"omnidl"}, "catadioptric-1": {"omnidl"},
    "double_sphere-0": KALIBR | {"omnidl"}, "double_sphere-1": KALIBR | {"omnidl"},
    "equirect-0": COLMAP | {"omnidl"},
    "eucm-0": COLMAP | KALIBR | {"omnidl"}, "eucm-1": COLMAP | KALIBR | {"omnidl"},
    **{f"fisheye-{i}": {"omnidl"} for i in range(4)},
    "fisheye624-0": {"omnidl"},  # max_fov 200 deg: COLMAP's RAD_TAN_THIN_PRISM_FISHEYE stops at 180
    "fov-0": COLMAP | KALIBR | {"omnidl"}, "fov-1": COLMAP | KALIBR | {"omnidl"},
    "kannala_brandt-0": {"kb_txt", "omnidl"},  # 195 deg: COLMAP/Kalibr/OpenCV/ORB-SLAM3 stop at 180
    "noncentral_catadioptric-0": {"omnidl"}, "noncentral_catadioptric-1": {"omnidl"},
    "noncentral_pano-0": {"omnidl"},
    "opencv-0": OPENCV | {"omnidl"}, "opencv-1": OPENCV | {"omnidl"},  # thin prism / k4..k6: OpenCV only
    "pinhole-0": COLMAP | KALIBR | OPENCV | {"orbslam3", "omnidl"},
    "scaramuzza-0": {"ocamcalib", "omnidl"},
    "unified-0": OPENCV | {"omnidl"},  # skew s != 0: Kalibr's omni has none
    "woodscape-0": {"omnidl"}, "woodscape-1": {"omnidl"},
    "resized-0": set(),  # not a registered family: not even omnidl YAML can rebuild it
}


def directions(n=8000, seed=7):
    """Random unit directions (not the writer's own Fibonacci grid) at distances 1 and 4."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, dtype=torch.float64, generator=g)
    d = d / d.norm(dim=-1, keepdim=True)
    return torch.cat([d, 4.0 * d])


def assert_same_view(a, b, tol=1e-9):
    """``a`` and ``b`` project the direction grid alike (mask exactly, pixels to ``tol``) and unproject alike."""
    pts = directions()
    uv_a, ok_a = a.project(pts)
    uv_b, ok_b = b.project(pts)
    assert torch.equal(ok_a, ok_b), f"{int((ok_a != ok_b).sum())} directions change validity"
    if ok_a.any():
        assert (uv_a - uv_b)[ok_a].abs().max() <= tol
    assert (a.width, a.height) == (b.width, b.height)
    uv = a.pixel_grid(torch.float64)[:: max(1, a.height // 48), :: max(1, a.width // 48)].reshape(-1, 2)
    assert torch.equal(a.unproject(uv).valid, b.unproject(uv).valid)


def save_or_refuse(cam, path, fmt):
    """``load(save(...))``, or ``None`` after checking the refusal names the format and the family and wrote nothing."""
    fam = type(cam).name
    try:
        out = save(cam, path, format=fmt)
    except UnsupportedModelError as e:
        assert repr(fmt) in str(e) or fmt in str(e), str(e)
        assert fam in str(e), str(e)
        assert not path.exists(), "a refused save left a file"
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (plausibility warnings are tested in tests/robustness)
        return load(out, format=fmt)


@pytest.mark.parametrize("writer", WRITERS, ids=[w[0] for w in WRITERS])
@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_every_camera_every_writer_round_trips_or_refuses(tmp_path, name, writer):
    wid, fname, fmt = writer
    cam = CAMERAS[name]
    back = save_or_refuse(cam, tmp_path / fname, fmt)
    expected = wid in ROUND_TRIPS.get(name, set())
    assert (back is not None) == expected, f"{name} x {wid}: {'refused' if back is None else 'round-tripped'}"
    if back is not None:
        assert_same_view(cam, back)


def test_the_table_covers_the_registry():
    assert set(ROUND_TRIPS) == set(CAMERAS)


# -- regressions (each fails on the main of before issue 48/49) -------------------------------------------
KB195 = KannalaBrandt(width=1080, height=960, fx=287.0, fy=287.0, cx=540.0, cy=480.0, max_fov=math.radians(195))


@pytest.mark.parametrize("fname,fmt", [("cameras.txt", "colmap"), ("cameras.bin", "colmap"),
                                       ("camchain.yaml", "kalibr"), ("calib.yaml", "opencv"), ("calib.xml", "opencv"),
                                       ("orb.yaml", "orbslam3")])
def test_kb_wider_than_180_is_refused_not_narrowed(tmp_path, fname, fmt):
    # before: written, and read back as a 180 deg lens (directions 90..97.5 deg off-axis silently lost)
    with pytest.raises(UnsupportedModelError, match=rf"'{fmt}'.*kannala_brandt.*max_fov = 195 deg.*180 deg"):
        save(KB195, tmp_path / fname, format=fmt)
    assert not (tmp_path / fname).exists()
    # the formats that hold a field of view keep it
    for name, other in (("kb.txt", "kb_txt"), ("cam.yaml", "omnidl")):
        assert_same_view(KB195, load(save(KB195, tmp_path / name, format=other)))


def test_kb_narrower_lens_is_refused_when_the_image_sees_the_difference(tmp_path):
    # a 165 deg lens whose image reaches 90 deg: COLMAP would read it back as 180 deg (wider)
    cam = KB195.replace(max_fov=math.radians(165))
    with pytest.raises(UnsupportedModelError, match=r"'colmap'.*max_fov 165 deg -> 180 deg.*directions change"):
        save(cam, tmp_path / "cameras.txt")
    # ... but a 165 deg lens on an image that ends at 70 deg off-axis loses nothing: written
    small = KannalaBrandt(width=640, height=480, fx=287.0, fy=287.0, cx=320.0, cy=240.0, max_fov=math.radians(165))
    assert_same_view(small, load(save(small, tmp_path / "small_cameras.txt", format="colmap")))


def test_refused_save_keeps_an_existing_file(tmp_path):
    path = tmp_path / "cameras.txt"
    save(Pinhole.example(), path)
    before = path.read_bytes()
    with pytest.raises(UnsupportedModelError):
        save(KB195, path)
    assert path.read_bytes() == before


def test_a_resized_camera_is_refused_instead_of_written_unreadable(tmp_path):
    # before: the omnidl YAML of a ResizedCamera was written and could not be loaded back
    with pytest.raises(UnsupportedModelError, match=r"'omnidl'.*'resized'.*does not read back"):
        save(ResizedCamera.example(), tmp_path / "cam.yaml")
    assert not (tmp_path / "cam.yaml").exists()


# -- YAML safety (issue 48 item 6) ---------------------------------------------------------------------------
UNSAFE = [
    ("cam.yaml", "type: pinhole\nwidth: !!python/object/apply:os.getpid []\nheight: 8\n"),
    ("camchain.yaml", "cam0: !!python/object:collections.OrderedDict\n  camera_model: pinhole\n"),
    ("calib.yaml", "%YAML:1.0\n---\ncamera_matrix: !!python/name:os.system\n"),
]


@pytest.mark.parametrize("name,text", UNSAFE, ids=[u[0] for u in UNSAFE])
def test_python_tags_are_refused_with_a_clear_error(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(io.UnsafeYAMLError, match=rf"{name}.*refused: the YAML tag '!!python/.*' would construct a "
                                              r"Python object"):
        load(path)
    for fmt in ("kalibr", "opencv", "orbslam3", "omnidl"):
        with pytest.raises(io.UnsafeYAMLError, match="refused"):
            load(path, format=fmt)
