"""OCamCalib model: calib_results.txt reader, OCamCalib's own formulas, OmniSCV's reference rays."""
import math

import numpy as np
import pytest
import torch

from omnidl.cameras import Scaramuzza, build, read_ocamcalib

# a small OCamCalib fixture (640 x 480; OmniSCV's default polynomial rescaled; invpol fitted offline)
CALIB = """#polynomial coefficients for the DIRECT mapping function (ocam_model.ss in MATLAB). These are used by cam2world

5 -1.710400e+02 0.000000e+00 2.386000e-03 -4.634700e-06 2.709370e-08 

#polynomial coefficients for the inverse mapping function (ocam_model.invpol in MATLAB). These are used by world2cam

11 244.150785 127.549032 -7.328587 23.941301 8.142444 -1.504587 4.224297 2.135959 0.147117 1.035284 0.491056 

#center: "row" and "column" coordinates (x, y) of the center of the image (NOT the principal point)

240.900000 320.600000

#affine parameters "c", "d", "e"

0.999924 0.000230 0.000168

#image size: "height" and "width"

480 640
"""


@pytest.fixture
def calib_file(tmp_path):
    path = tmp_path / "calib_results.txt"
    path.write_text(CALIB)
    return path


def _ocam_cam2world(row, col, pol, xc, yc, c, d, e):
    """OCamCalib's cam2world as published (point2D = (row, col), 1-based MATLAB pixels)."""
    invdet = 1 / (c - d * e)
    xp = invdet * ((row - xc) - d * (col - yc))
    yp = invdet * (-e * (row - xc) + c * (col - yc))
    zp = np.polyval(pol[::-1], math.hypot(xp, yp))
    v = np.array([xp, yp, zp])
    return v / np.linalg.norm(v)


def _ocam_world2cam(p, invpol, xc, yc, c, d, e):
    norm = math.hypot(p[0], p[1])
    theta = math.atan(p[2] / norm)
    rho = np.polyval(invpol[::-1], theta)
    x, y = p[0] / norm * rho, p[1] / norm * rho
    return x * c + y * d + xc, x * e + y + yc


def test_reader_and_conventions_match_ocamcalib(calib_file):
    cam = build({"type": "scaramuzza", "calib_file": str(calib_file)})
    f = read_ocamcalib(calib_file)
    assert (cam.width, cam.height) == (640, 480) and len(cam.pol) == 5 and len(cam.invpol) == 11
    # row/column swap and 1-based MATLAB pixel centres
    assert (cam.cx, cam.cy) == (320.6 - 0.5, 240.9 - 0.5) == (f["cx"], f["cy"])
    g = np.random.default_rng(0)
    for _ in range(50):
        row, col = g.uniform(1, 480), g.uniform(1, 640)
        ocam = _ocam_cam2world(row, col, cam.pol, 240.9, 320.6, cam.c, cam.d, cam.e)
        # OCamCalib frame (down, right, backward) -> omnidl (right, down, forward)
        want = np.array([ocam[1], ocam[0], -ocam[2]])
        ray = cam.unproject(torch.tensor([col - 0.5, row - 0.5], dtype=torch.float64))
        assert ray.valid and np.abs(ray.direction.numpy() - want).max() < 1e-13
        # forward: OCamCalib's world2cam with the file's invpol agrees up to the invpol fit error
        r_ocam, c_ocam = _ocam_world2cam(ocam * 2.5, cam.invpol, 240.9, 320.6, cam.c, cam.d, cam.e)
        uv, valid = cam.project(torch.from_numpy(want * 2.5))
        assert valid and abs(float(uv[0]) - (c_ocam - 0.5)) < 0.05 and abs(float(uv[1]) - (r_ocam - 0.5)) < 0.05
        assert abs(float(uv[0]) - (col - 0.5)) < 1e-9 and abs(float(uv[1]) - (row - 0.5)) < 1e-9


def test_fitted_invpol_when_missing(calib_file):
    cam = Scaramuzza.from_file(calib_file).replace(invpol=())
    fit = cam.inverse_polynomial
    assert len(fit) > 3
    uv = cam.pixel_grid(torch.float64)[::37, ::41].reshape(-1, 2)
    uv2, valid = cam.project(cam.unproject(uv).direction)
    assert valid.all() and (uv2 - uv).abs().max() < 1e-9


def test_matches_omniscv_reference_rays():
    # docs/design.md#omniscv-reference-rays: OmniSCV default polynomial, 1024 x 1024, centre (512, 512)
    cam = Scaramuzza(width=1024, height=1024, pol=(-2.736690e+02, 0, 1.491215e-03, -1.810410e-06, 6.614668e-09),
                     cx=512.0, cy=512.0)
    pix = torch.tensor([[512, 512], [612, 512], [512, 300], [900, 900], [1000, 512]], dtype=torch.float64)
    want = torch.tensor([[0, 0, 1], [0.359092, 0, 0.933302], [0, -0.709552, 0.704653],
                         [0.534203, 0.534203, -0.655175], [0.892816, 0, -0.450422]], dtype=torch.float64)
    rays = cam.unproject(pix)
    assert rays.valid.all() and (rays.direction - want).abs().max() < 2e-6


def test_bad_files(tmp_path):
    p = tmp_path / "broken_calib.txt"
    p.write_text(CALIB.replace("5 -1.710400e+02", "6 -1.710400e+02"))
    with pytest.raises(ValueError, match="broken_calib.txt.*pol"):
        read_ocamcalib(p)
    p.write_text("\n".join(CALIB.splitlines()[:8]))
    with pytest.raises(ValueError, match="broken_calib.txt.*5 data lines"):
        read_ocamcalib(p)
    with pytest.raises(ValueError, match="a0 < 0"):
        Scaramuzza(width=8, height=8, pol=(1.0, 0.0))


# The toolbox's exporter states the C convention above the centre line and writes xc - 1, yc - 1.
TOOLBOX_CENTRE_COMMENT = ('#center: "row" and "column" coordinates (x, y) of the center of the image. '
                          'In C the coordinates start from 0')


def _with_centre(comment, xc, yc):
    lines = CALIB.splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.startswith("#center"))
    lines[i] = comment
    lines[i + 2] = f"{xc!r} {yc!r}"
    return "\n".join(lines) + "\n"


def test_toolbox_file_with_a_known_centre_lands_exactly_there(tmp_path):
    # principal point at omnidl pixel (u, v) = (321.25, 239.75): 0-based C pixel coordinates (col, row) =
    # (320.75, 239.25), written by the toolbox as "row col" = xc-1, yc-1 of MATLAB's 1-based values
    path = tmp_path / "calib_results.txt"
    path.write_text(_with_centre(TOOLBOX_CENTRE_COMMENT, 239.25, 320.75))
    cam = Scaramuzza.from_file(path)
    assert (cam.cx, cam.cy) == (321.25, 239.75)
    assert build({"type": "scaramuzza", "calib_file": str(path)}) == cam
    ray = cam.unproject(torch.tensor([321.25, 239.75], dtype=torch.float64))
    assert ray.valid and ray.direction.tolist() == [0.0, 0.0, 1.0]
    uv, valid = cam.project(torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64))
    assert valid and uv.tolist() == [321.25, 239.75]
    # the same numbers in a file that states MATLAB's 1-based convention, and forced conventions
    path.write_text(_with_centre("#center (row, column), MATLAB 1-based pixel coordinates", 239.25, 320.75))
    assert (read_ocamcalib(path)["cx"], read_ocamcalib(path)["cy"]) == (320.25, 238.75)
    assert read_ocamcalib(path, one_based=False)["cx"] == 321.25
    assert Scaramuzza.from_config({"calib_file": str(path), "one_based": False}).cy == 239.75


def test_centre_convention_from_the_comment():
    from omnidl.cameras.scaramuzza import centre_convention
    assert centre_convention(TOOLBOX_CENTRE_COMMENT) is False
    assert centre_convention("# centre, zero-based") is False
    assert centre_convention("# centre, 1-based (MATLAB)") is True
    assert centre_convention('#center: "row" and "column" coordinates (x, y) of the center of the image') is None
