"""omnidl.cameras.fit (omnidl/cameras/fitting.py): model conversion by least squares over the source's rays."""
import math

import pytest
import torch

from omnidl.cameras import KannalaBrandt, Pinhole, Unified, list_cameras, resolve_camera
from omnidl.cameras.fitting import FitReport, fit

# a KITTI-360-like unified camera without tangential terms (Kannala-Brandt is radially symmetric)
UNIFIED = Unified(width=352, height=352, xi=1.2, fx=320.0, fy=320.0, cx=176.0, cy=176.0, k1=-0.05, k2=0.02)


def _ray_error_deg(fitted, source, n=400):
    uv = source.sample_points(n, generator=torch.Generator().manual_seed(0))
    a, b = source.unproject(uv), fitted.unproject(uv)
    ok = a.valid & b.valid
    cos = (a.direction * b.direction).sum(-1).clamp(-1, 1)
    return float(torch.rad2deg(torch.acos(cos[ok])).max()), int((~ok).sum())


def test_same_family_recovers_the_parameters():
    kb = resolve_camera("kb_f195").resized(270, 240)
    cam, rep = fit("kannala_brandt", kb.base.replace(width=270, height=240, fx=71.75, fy=71.75, cx=135.0, cy=120.0),
                   grid=24)
    assert isinstance(rep, FitReport) and rep.family == "kannala_brandt" and "k0" not in rep.fitted
    assert rep.rms_px < 1e-6 and rep.num_invalid == 0 and rep.num_samples > 300
    assert abs(cam.fx - 71.75) < 1e-6 and abs(cam.cx - 135.0) < 1e-6 and (cam.width, cam.height) == (270, 240)


def test_unified_to_kannala_brandt():
    cam, rep = fit("kannala_brandt", UNIFIED, grid=32)
    assert isinstance(cam, KannalaBrandt) and (cam.width, cam.height) == (352, 352)
    assert rep.rms_px < 0.05 and rep.max_px < 0.2, rep
    err, missing = _ray_error_deg(cam, UNIFIED)
    assert err < 0.05 and missing == 0


def test_kannala_brandt_to_unified():
    kb = resolve_camera("kb_f195")
    cam, rep = fit("unified", kb, grid=32)
    assert isinstance(cam, Unified) and rep.num_invalid == 0
    assert rep.rms_px < 0.05 and rep.max_px < 0.1, rep
    assert abs(cam.cx - 540) < 1e-3 and abs(cam.cy - 480) < 1e-3


@pytest.mark.parametrize("family", ["double_sphere", "eucm"])
def test_fisheye_families_fitted_to_the_195_degree_kb_camera(family):
    if family not in list_cameras():
        pytest.skip(f"{family!r} is not registered yet")
    kb = resolve_camera("kb_f195")
    cam, rep = fit(family, kb)
    assert rep.num_invalid == 0 and rep.num_samples > 1000
    print(f"{family}: rms {rep.rms_px:.4f} px, max {rep.max_px:.4f} px over {rep.num_samples} samples")
    if family == "double_sphere":
        assert rep.rms_px < 0.1 and rep.max_px < 0.1, rep
    else:
        # EUCM's radial curve (alpha, beta, f) cannot follow an equidistant 195 deg lens closer than
        # ~0.15 px RMS / 0.43 px max: every start converges to the same optimum (alpha 0.596, beta 1.149)
        assert rep.rms_px < 0.16 and rep.max_px < 0.45, rep


def test_errors():
    with pytest.raises(ValueError, match="not central"):
        fit("kannala_brandt", resolve_camera("noncentral_pano"))
    with pytest.raises(ValueError, match=r"unknown field\(s\) \['focal'\]"):
        fit("pinhole", UNIFIED, focal=3.0)
    with pytest.raises(KeyError, match="no_such"):
        fit("no_such", UNIFIED)
    cam, rep = fit(Pinhole, Pinhole(width=40, height=30, fx=30.0, fy=31.0, cx=20.5, cy=14.5), grid=8, fixed=("fy",),
                   fy=31.0)
    assert rep.fitted == ("fx", "cx", "cy") and rep.rms_px < 1e-8 and math.isclose(cam.fx, 30.0)
