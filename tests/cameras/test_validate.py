"""The one parameter-validation layer (omnidl.cameras.validate), checked over every registered family."""
import dataclasses
import math
import re

import pytest
import torch

from omnidl.cameras import Camera, Equirectangular, Pinhole, build, get_camera_class, list_cameras
from omnidl.cameras.validate import NONNEGATIVE, POSITIVE, Domain, between, check_size

FAMILIES = list_cameras()


def _float_fields(cam):
    return [f.name for f in dataclasses.fields(cam) if str(f.type).replace(" ", "") == "float"]


def outside(domain: Domain) -> list[float]:
    """Values just outside ``domain`` (its open ends themselves, or one past its closed ends)."""
    vals = []
    if math.isfinite(domain.lo):
        vals.append(domain.lo - 1.0 if domain.lo_closed else domain.lo)
    if math.isfinite(domain.hi):
        vals.append(domain.hi + 1.0 if domain.hi_closed else domain.hi)
    return vals


def test_every_family_declares_a_domain_or_only_finiteness():
    for name in FAMILIES:
        cls = get_camera_class(name)
        for field in cls.domains:
            assert field in {f.name for f in dataclasses.fields(cls)}, (name, field)
        for ex in cls.examples():                           # the examples pass their own checks
            for field, dom in cls.domains.items():
                assert dom.contains(float(getattr(ex, field))), (name, field)


@pytest.mark.parametrize("name", FAMILIES)
@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf"), "abc", None])
def test_every_float_field_must_be_finite(name, value):
    ex = get_camera_class(name).example()
    for field in _float_fields(ex):
        with pytest.raises(ValueError, match=rf"{field}.*(finite|must be).*{re.escape(repr(value))}"):
            dataclasses.replace(ex, **{field: value})


@pytest.mark.parametrize("name", FAMILIES)
def test_every_declared_domain_is_enforced(name):
    cls = get_camera_class(name)
    ex = cls.example()
    for field, dom in cls.domains.items():
        for bad in outside(dom):
            with pytest.raises(ValueError, match=rf"camera.*{field}"):
                dataclasses.replace(ex, **{field: bad})


@pytest.mark.parametrize("name", FAMILIES)
@pytest.mark.parametrize("size", [0, -8, 64.7, "64", True, float("nan")])
def test_image_size_is_a_positive_integer(name, size):
    ex = get_camera_class(name).example()
    for side in ("width", "height"):
        with pytest.raises(ValueError, match=rf"{name} camera: {side} must be a positive integer.*got"):
            dataclasses.replace(ex, **{side: size})


@pytest.mark.parametrize("name", FAMILIES)
def test_integral_sizes_are_stored_as_int_and_resized_checks_its_arguments(name):
    ex = get_camera_class(name).example()
    cam = dataclasses.replace(ex, width=float(ex.width), height=torch.tensor(ex.height))
    assert type(cam.width) is int and type(cam.height) is int and cam == ex
    for w, h in ((0, 0), (-4, -2), (8.5, 8), ("8", 8)):
        with pytest.raises(ValueError, match=rf"{name} camera: resized\(.*\): (width|height) must be a positive"):
            ex.resized(w, h)
    with pytest.raises(ValueError, match="pad_right must be a finite number"):
        ex.resized(8, 8, pad_right=-ex.width)
    r = ex.resized(ex.width // 2, ex.height // 2)
    with pytest.raises(ValueError, match=r"resized camera: resized\(0, 3\): width must be a positive integer"):
        r.resized(0, 3)


def test_resized_camera_domains_and_base():
    base = Equirectangular(width=16, height=8)
    with pytest.raises(ValueError, match="scale_x must be > 0, got 0.0"):
        dataclasses.replace(base.resized(8, 4), scale_x=0.0)
    with pytest.raises(ValueError, match="base must be a Camera"):
        dataclasses.replace(base.resized(8, 4), base=None)


def test_build_and_subclasses_use_the_same_layer():
    with pytest.raises(ValueError, match=r"pinhole camera: fx must be > 0, got -50"):
        build({"type": "pinhole", "width": 8, "height": 8, "fx": -50.0, "fy": 1.0})
    with pytest.raises(ValueError, match=r"equirect camera: width must be a positive integer .*got 0"):
        build({"type": "equirect", "width": 0, "height": 8})

    @dataclasses.dataclass(frozen=True)
    class Unregistered(Camera):                          # no registry name: the class name is used
        f: float = 1.0

    with pytest.raises(ValueError, match="Unregistered camera: f must be finite"):
        Unregistered(width=4, height=4, f=float("nan"))


def test_domain_helpers():
    assert POSITIVE.describe() == "> 0" and NONNEGATIVE.describe() == ">= 0"
    assert between(0, 1).describe() == "in [0, 1]" and between(0, 1, "(]").contains(1.0)
    assert not between(0, 1, "()").contains(0.0)
    assert check_size("x", 4.0, 3) == (4, 3)
    with pytest.raises(ValueError, match=r"x: height must be a positive integer \(>= 1 pixel\), got 0"):
        check_size("x", 4, 0)


@pytest.mark.parametrize("name", FAMILIES)
def test_non_finite_inputs_give_invalid_finite_outputs(name):
    """project/unproject of NaN (and inf) inputs: never a NaN/inf pixel or ray, NaN inputs never valid."""
    nan, inf = float("nan"), float("inf")
    pts = torch.tensor([[nan, 0, 1], [0, nan, 1], [0, 0, nan], [inf, 0, 1], [0, -inf, 1], [0, 0, inf]],
                       dtype=torch.float64)
    pix = torch.tensor([[nan, 1.0], [1.0, nan], [inf, 2.0], [3.0, -inf]], dtype=torch.float64)
    for cam in get_camera_class(name).examples():
        uv, valid = cam.project(pts)
        assert torch.isfinite(uv).all() and not valid[:3].any()
        rays = cam.unproject(pix)
        assert torch.isfinite(rays.origin).all() and torch.isfinite(rays.direction).all()
        assert not rays.valid.any()


def test_pinhole_fx_zero_was_accepted_before():
    """Issue 14: ``fx: 0`` built a camera projecting every point to cx; ``fx: -50`` a mirrored one."""
    with pytest.raises(ValueError, match="pinhole camera: fx must be > 0, got 0"):
        Pinhole(width=8, height=8, fx=0.0, fy=1.0)

