import json

import numpy as np
import pytest
import torch

from omnidl.cameras import Equirectangular
from omnidl.viz import (box_edges, class_legend, depth_colorbar, depth_to_points, draw_segments_3d, ply_frame,
                        prediction_figure, read_depth_png16, read_ply, to_gravity_y_up, write_depth_png16,
                        write_ply, write_semantic_png)
from omnidl.viz.figure import nice_ticks, title_height


def test_prediction_figure_is_full_resolution_with_titles_bar_and_legend():
    H, W = 96, 192
    img = torch.rand(3, H, W)
    depth = torch.rand(1, H // 2, W // 2) * 5 + 0.5            # a lower-resolution prediction is upsampled
    sem = torch.randint(0, 14, (H, W))
    fig = prediction_figure(img, depth=depth, semantic=sem, gt_depth=depth, gt_semantic=sem)
    th = title_height(H)
    assert fig.shape[0] == 3 and fig.shape[1] >= H + th
    assert fig.shape[2] > 5 * W                                  # 5 full-size panels + the key column
    assert torch.allclose(fig[:, th:th + H, :W], img, atol=1 / 255)  # the input panel is not resized
    assert (fig[:, :th, :W] < 0.5).any()                         # a title is drawn above it
    key = fig[:, :, 5 * W + 16:]
    assert key.std() > 0.05                                      # colour bar + legend drawn


def test_colorbar_ticks_and_legend_rows():
    assert nice_ticks(0, 7.3) == [0, 2, 4, 6]
    assert nice_ticks(0.5, 1.0) == [0.6, 0.8, 1.0]
    bar = depth_colorbar(200, 7.3)
    assert bar.shape[1] == 200 and bar.shape[0] == 3
    leg = class_legend([1, 12, 9], 200)
    small = class_legend(list(range(14)), 60)                   # not enough height: more columns
    assert small.shape[2] > leg.shape[2]


def test_depth_png16_roundtrip_and_scale_file(tmp_path):
    d = torch.tensor([[0.0, 1.2345, float("nan"), 10.0]])
    p, scale = write_depth_png16(tmp_path / "x_depth.png", d)
    assert scale == 1e-3
    side = json.loads((tmp_path / "x_depth.json").read_text())
    assert side["scale"] == 1e-3 and side["unit"] == "m" and side["invalid"] == 0
    back = read_depth_png16(p)
    assert back[0, 0] == 0 and back[0, 2] == 0 and abs(back[0, 1] - 1.2345) <= 5e-4 and abs(back[0, 3] - 10) < 1e-6
    _, scale = write_depth_png16(tmp_path / "far.png", torch.tensor([[100.0, 50.0]]))  # > 65.535 m
    assert scale == pytest.approx(100 / 65535)
    assert abs(read_depth_png16(tmp_path / "far.png")[0, 0] - 100) < 1e-3
    (tmp_path / "far.json").unlink()
    with pytest.raises(FileNotFoundError, match="far.json"):
        read_depth_png16(tmp_path / "far.png")


def test_semantic_png(tmp_path):
    import cv2
    lab = torch.randint(0, 14, (8, 16))
    paths = write_semantic_png(tmp_path / "s.png", lab)
    assert np.array_equal(cv2.imread(str(paths[0]), cv2.IMREAD_UNCHANGED), lab.numpy().astype(np.uint8))
    assert cv2.imread(str(paths[1])).shape == (8, 16, 3)
    with pytest.raises(ValueError, match=r"class ids must be in \[0, 255\]"):
        write_semantic_png(tmp_path / "bad.png", torch.full((2, 2), 300))


def test_ply_gravity_y_up_frame(tmp_path):
    cam = Equirectangular(width=16, height=8)
    depth = torch.full((1, 8, 16), 2.0)
    cam_pts, _ = depth_to_points(depth, cam)
    up_pts, _ = depth_to_points(depth, cam, frame="gravity_y_up")
    # upright: the top rows (looking up) have y > 0, the centre column looks along -z
    assert torch.allclose(up_pts, cam_pts * torch.tensor([1.0, -1.0, -1.0]))
    assert up_pts[:16, 1].min() > 1.5 and up_pts[-16:, 1].max() < -1.5
    # a tilted camera: R_up_cam rotates its points into the upright frame first
    R = torch.tensor([[1.0, 0, 0], [0, 0.8, -0.6], [0, 0.6, 0.8]])
    tilt_pts, _ = depth_to_points(depth, cam, frame="gravity_y_up", R_up_cam=R)
    assert torch.allclose(tilt_pts, to_gravity_y_up(cam_pts @ R.T), atol=1e-6)
    write_ply(tmp_path / "p.ply", up_pts, frame="gravity_y_up")
    assert ply_frame(tmp_path / "p.ply") == "gravity_y_up"
    assert np.allclose(read_ply(tmp_path / "p.ply")[0], up_pts.numpy())
    with pytest.raises(ValueError, match="frame must be one of"):
        depth_to_points(depth, cam, frame="z_up")


def test_wireframe_draws_room_edges_on_panorama():
    cam = Equirectangular(width=128, height=64)
    floor = np.array([[-2, 1.5, -2], [2, 1.5, -2], [2, 1.5, 2], [-2, 1.5, 2]], float)  # y down: floor at +1.5
    ceil = floor.copy()
    ceil[:, 1] = -1.0
    edges = box_edges(floor, ceil)
    assert edges.shape == (12, 2, 3)
    out = draw_segments_3d(torch.zeros(3, 64, 128), edges, cam, color=(0, 1, 0))
    green = out[1] > 0.5
    assert green[:32].any() and green[32:].any() and out[0].max() == 0
    with pytest.raises(ValueError, match="camera is 128x64"):
        draw_segments_3d(torch.zeros(3, 8, 8), edges, cam)


def test_curve_panels_one_per_unit(tmp_path):
    import matplotlib.image as mpimg

    from omnidl.viz import plot_curve_panels
    p = plot_curve_panels(tmp_path / "rot.png", [0, 10, 20], {"metres": {"rmse": [0.3, 0.4, 0.6]},
                                                             "fraction": {"delta1": [0.9, 0.8, 0.7]}}, "deg")
    img = mpimg.imread(p)
    assert img.shape[1] > 1.6 * img.shape[0]          # two panels side by side
    with pytest.raises(ValueError, match="no curves"):
        plot_curve_panels(tmp_path / "x.png", [0], {"metres": {}})


def test_figure_visualizer_stacks_full_size_figures():
    from omnidl.viz import FigureVisualizer
    b = {"image": torch.rand(3, 3, 32, 64), "depth": torch.rand(3, 1, 32, 64) + 1,
         "semantic": torch.randint(0, 14, (3, 32, 64))}
    out = {"depth": torch.rand(3, 1, 32, 64), "semantic": torch.randn(3, 14, 32, 64)}
    pic = FigureVisualizer(max_images=2)(out, b)
    one = FigureVisualizer(max_images=1)(out, b)
    assert pic.shape[1] == 2 * one.shape[1] and pic.shape[2] > 5 * 64 and 0 <= pic.min() and pic.max() <= 1
    only_depth = FigureVisualizer()({"depth": out["depth"]}, {"image": b["image"]})
    assert only_depth.shape[2] < one.shape[2]
