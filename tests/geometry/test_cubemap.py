"""Cube maps against py360convert (e2c, c2e), round trips, face order and orientation."""
import math

import numpy as np
import py360convert
import pytest
import torch

from .geom_helpers import render, texture
from omnidl.cameras import Equirectangular, Pinhole
from omnidl.geometry import (FACE_NAMES, cube_face_camera, cube_face_rotations, cubemap_to_camera,
                             cubemap_to_equirect, equirect_to_cubemap, euler_to_matrix, reproject)

D = torch.float64
W, H, F = 256, 128, 64


@pytest.fixture(scope="module")
def pano():
    return render(Equirectangular(width=W, height=H))


def py360_e2c_face_camera(f):
    """py360convert's e2c samples ``linspace(-0.5, 0.5, F)`` of the unit cube: pixel centres on the
    face edges, i.e. a pinhole with ``f = (F - 1) / 2`` and centre ``F / 2``."""
    return Pinhole(width=f, height=f, fx=(f - 1) / 2, fy=(f - 1) / 2, cx=f / 2, cy=f / 2)


def py360_c2e_face_camera(f):
    """py360convert's c2e maps a direction to the face index ``F/2 (x + 1)`` (index = our pixel
    coordinate - 0.5): a pinhole with ``f = F / 2`` and centre ``F / 2 + 0.5``."""
    return Pinhole(width=f, height=f, fx=f / 2, fy=f / 2, cx=f / 2 + 0.5, cy=f / 2 + 0.5)


def test_e2c_matches_py360convert(pano):
    ref = np.stack(py360convert.e2c(pano[0, 0].float().numpy(), face_w=F, cube_format="list"))
    ours = equirect_to_cubemap(pano.float(), F, face_camera=py360_e2c_face_camera(F))
    assert ours.shape == (1, 6, 1, F, F)
    for k in range(6):  # same face order (F R B L U D) and orientation
        mad = np.abs(ours[0, k, 0].numpy() - ref[k]).mean()
        assert mad < 1.2, (FACE_NAMES[k], mad)


def test_c2e_matches_py360convert(pano):
    faces = np.stack(py360convert.e2c(pano[0, 0].float().numpy(), face_w=F, cube_format="list"))
    ref = py360convert.c2e(list(faces), H, W, cube_format="list")
    ours = cubemap_to_equirect(torch.from_numpy(faces)[None, :, None], W, H,
                               face_camera=py360_c2e_face_camera(F))
    mad = np.abs(ours[0, 0].numpy() - ref).mean()
    assert mad < 1.2, mad


def test_round_trip_and_analytic_faces(pano):
    faces = equirect_to_cubemap(pano, F)
    cam = cube_face_camera(F)
    Rf = cube_face_rotations(D)
    d = cam.unproject_grid(dtype=D).direction
    for k in range(6):  # each face shows the texture in its direction R_pano_face @ d
        true = texture(torch.einsum("ij,hwj->hwi", Rf[k], d))
        assert (faces[0, k, 0] - true).abs().mean() < 0.3, FACE_NAMES[k]
    back = cubemap_to_equirect(faces, W, H)
    assert (back - pano).abs().mean() < 0.5


def test_face_directions_and_orientation():
    Rf = cube_face_rotations(D)
    fwd = Rf[:, :, 2]  # optical axes
    expected = torch.tensor([[0, 0, 1], [1, 0, 0], [0, 0, -1], [-1, 0, 0], [0, -1, 0], [0, 1, 0]], dtype=D)
    assert torch.equal(fwd, expected)
    assert torch.allclose(torch.linalg.det(Rf), torch.ones(6, dtype=D))
    # the up face's image-down axis is +z (its bottom edge meets the front face), down face's is -z
    assert torch.equal(Rf[4, :, 1], torch.tensor([0, 0, 1.0], dtype=D))
    assert torch.equal(Rf[5, :, 1], torch.tensor([0, 0, -1.0], dtype=D))
    # side faces keep image-down = camera +y (down)
    assert (Rf[:4, :, 1] == torch.tensor([0, 1.0, 0], dtype=D)).all()


def test_labels_and_cubemap_to_any_camera(pano):
    lab = torch.randint(0, 13, (2, 1, 64, 128))
    faces = equirect_to_cubemap(lab, 32, mode="nearest")
    assert faces.shape == (2, 6, 1, 32, 32)
    assert faces.dtype == torch.int64 and set(faces.unique().tolist()) <= set(lab.unique().tolist())
    back = cubemap_to_equirect(faces, 128, 64, mode="nearest")
    assert (back == lab).double().mean() > 0.5
    # a perspective view rendered from the cube map equals the one from the panorama
    cam = Pinhole.from_fov(40, 30, math.radians(70))
    R = euler_to_matrix(torch.tensor(0.1, dtype=D), torch.tensor(0.6, dtype=D), torch.tensor(-2.0, dtype=D))
    a, va = cubemap_to_camera(equirect_to_cubemap(pano, 64), cam, R)
    b, vb = reproject(pano, Equirectangular(width=W, height=H), cam, R)
    assert va.all() and vb.all() and (a - b).abs().mean() < 0.6
    with pytest.raises(ValueError, match=r"\(B, 6, C, F, F\)"):
        cubemap_to_camera(torch.zeros(1, 5, 1, 8, 8), cam)
