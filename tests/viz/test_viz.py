import matplotlib
import numpy as np
import pytest
import torch

from omnidl.cameras import Equirectangular
from omnidl.classes import CLASS_COLORS
from omnidl.viz import (PanoramaVisualizer, depth_to_color, depth_to_points, make_grid, overlay, plot_curves,
                        read_ply, semantic_to_color, to_uint8_bgr, write_ply)


def test_depth_colormap_matches_matplotlib_turbo_and_blacks_invalid():
    d = torch.tensor([[0.0, 1.0, 2.0, 4.0]])
    rgb = depth_to_color(d, vmax=4.0)
    ref = matplotlib.colormaps["turbo"](np.linspace(0, 1, 256))[:, :3]
    assert torch.equal(rgb[:, 0, 0], torch.zeros(3))  # invalid
    for j, t in ((1, 0.25), (2, 0.5), (3, 1.0)):
        assert np.allclose(rgb[:, 0, j].numpy(), ref[int(round(t * 255))], atol=1e-6)
    assert depth_to_color(torch.full((1, 2, 2), float("nan"))).abs().sum() == 0


def test_semantic_palette_and_logits():
    labels = torch.arange(14).reshape(2, 7)
    rgb = semantic_to_color(labels)
    assert torch.allclose(rgb[:, 1, 5] * 255, torch.tensor(CLASS_COLORS[12], dtype=torch.float32))
    logits = torch.nn.functional.one_hot(labels, 14).permute(2, 0, 1).float()
    assert torch.equal(semantic_to_color(logits), rgb)


def test_overlay_and_grid():
    img = torch.zeros(3, 4, 8)
    col = torch.ones(3, 4, 8)
    assert torch.allclose(overlay(img, col, 0.25), torch.full((3, 4, 8), 0.25))
    g = make_grid([[img, col[:1]], [col]], pad=1)
    assert g.shape == (3, 9, 17)
    assert g[:, 0, 9:].eq(1).all() and g[:, 5:, 9:].eq(1).all()  # padding value fills the missing panel
    bgr = to_uint8_bgr(torch.stack([torch.ones(2, 2), torch.zeros(2, 2), torch.zeros(2, 2)]))
    assert bgr.dtype == np.uint8 and bgr[0, 0].tolist() == [0, 0, 255]


def test_visualizer_panels():
    b = {"image": torch.rand(3, 3, 8, 16), "depth": torch.rand(3, 1, 8, 16) + 1,
         "semantic": torch.randint(0, 14, (3, 8, 16))}
    out = {"depth": torch.rand(3, 1, 8, 16), "semantic": torch.randn(3, 14, 8, 16)}
    pic = PanoramaVisualizer(max_images=2)(out, b)
    assert pic.shape == (3, 2 * 8 + 2, 5 * 16 + 4 * 2) and 0 <= pic.min() and pic.max() <= 1
    pic = PanoramaVisualizer(max_images=1)({"depth": out["depth"]}, {"image": b["image"]})
    assert pic.shape == (3, 8, 2 * 16 + 2)


def test_point_cloud_through_camera_and_ply_roundtrip(tmp_path):
    cam = Equirectangular(width=16, height=8)
    depth = torch.full((1, 8, 16), 2.0)
    depth[0, 0, 0] = 0  # invalid
    img = torch.rand(3, 8, 16)
    pts, cols = depth_to_points(depth, cam, img)
    assert pts.shape == (127, 3)
    assert torch.allclose(pts.norm(dim=1), torch.full((127,), 2.0), atol=1e-5)
    # the pixel (row 4, col 8) is just below the equator, looking along +z
    i = 4 * 16 + 8 - 1
    lat = np.pi / 2 - np.pi * 4.5 / 8
    lon = 2 * np.pi * 8.5 / 16 - np.pi
    ref = 2 * np.array([np.cos(lat) * np.sin(lon), -np.sin(lat), np.cos(lat) * np.cos(lon)])
    assert np.allclose(pts[i].numpy(), ref, atol=1e-5)
    write_ply(tmp_path / "p.ply", pts, cols)
    p2, c2 = read_ply(tmp_path / "p.ply")
    assert np.allclose(p2, pts.numpy()) and np.array_equal(c2, (cols.numpy() * 255).round().astype(np.uint8))
    head = (tmp_path / "p.ply").read_bytes()[:200].decode("ascii", "ignore")
    assert "element vertex 127" in head and "property uchar red" in head
    with pytest.raises(ValueError, match="camera is 16x8"):
        depth_to_points(torch.ones(1, 4, 4), cam)
    write_ply(tmp_path / "nocolor.ply", np.zeros((2, 3)))
    assert read_ply(tmp_path / "nocolor.ply")[1] is None


def test_plot_curves(tmp_path):
    p = plot_curves(tmp_path / "r.png", [0, 5, 10], {"delta1": [0.9, 0.8, 0.7]}, "deg", "value")
    assert p.stat().st_size > 1000 and not list(tmp_path.glob(".*tmp"))
