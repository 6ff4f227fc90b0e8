"""``omnidl predict layout`` on a tilted panorama gives the layout of its upright original, in the input's frame.

The network is a stand-in that returns the ground-truth boundary and corners of the upright room (whatever
it is shown), so the test measures the command's own geometry: levelling the tilted copy, running the layout
on it and taking the corners back into the tilted input."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from omnidl.apps.predict.loader import Predictor
from omnidl.apps.predict.run import UprightPolicy, predict_layout
from omnidl.cameras import Equirectangular
from omnidl.geometry.boundary import rows_to_angles
from omnidl.geometry.rotations import euler_to_matrix
from omnidl.geometry.upright import to_input_frame
from omnidl.synth import render_sample
from omnidl.viz import read_glb


class OracleLayoutNet(torch.nn.Module):
    """Returns fixed HorizonNet outputs ``boundary (1, 2, W)`` radians and ``corner (1, 1, W)`` logits."""

    def __init__(self, boundary: torch.Tensor, corner_prob: torch.Tensor) -> None:
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(1))
        self.boundary, self.corner = boundary, torch.logit(corner_prob.clamp(1e-4, 1 - 1e-4))

    def forward(self, x):
        return {"boundary": self.boundary[None] + 0 * self.w, "corner": self.corner.reshape(1, 1, -1)}


@pytest.mark.slow
def test_tilted_panorama_layout_matches_the_upright_one(tmp_path):
    W, H = 512, 256
    cam = Equirectangular(width=W, height=H)
    s = render_sample(cam, 11, "test", 2, rotation="upright", furniture=True)
    net = OracleLayoutNet(rows_to_angles(s["boundary"].float(), H), s["corner_heat"][0])
    pred = Predictor(net, "horizonnet", H, W, None, "oracle", info={"outputs": ("boundary", "corner")})
    R = euler_to_matrix(math.radians(14.0), math.radians(-9.0), 0.0).double()    # R_up_cam of the tilted copy
    tilted = to_input_frame(s["image"], R).clamp(0, 1)
    predict_layout(pred, "up", s["image"], tmp_path, UprightPolicy(), camera_height=float(s["camera_height"]))
    files = predict_layout(pred, "tilt", tilted, tmp_path, UprightPolicy(), camera_height=float(s["camera_height"]),
                           mesh=("glb", "obj"))
    up = json.loads((tmp_path / "up_layout.json").read_text())
    tl = json.loads((tmp_path / "tilt_layout.json").read_text())
    assert up["layout"]["ok"] and tl["layout"]["ok"] and not up["upright"]["rotated"] and tl["upright"]["rotated"]
    assert len(tl["layout"]["corners_2d"]) == len(up["layout"]["corners_2d"])
    # where the upright room's corners really are in the tilted image vs where the command put them
    fl = np.asarray(up["input_frame"]["floor_corners"])
    ce = np.asarray(up["input_frame"]["ceiling_corners"])
    true_uv = torch.cat([cam.project(torch.from_numpy(p) @ R)[0] for p in (fl, ce)])     # R^T @ X, row-wise
    got_uv = torch.tensor(tl["input_frame"]["floor_corners_uv"] + tl["input_frame"]["ceiling_corners_uv"])
    d = got_uv - true_uv
    d[:, 0] = (d[:, 0] + W / 2) % W - W / 2
    corner_error = float(d.norm(dim=-1).mean() / math.hypot(W, H) * 100)
    print(f"corner error tilted vs upright through predict layout: {corner_error:.3f} % of the diagonal")
    assert corner_error < 0.5
    for f in ("tilt_layout.obj", "tilt_wireframe.png", "tilt_figure.png", "tilt_room.obj", "tilt_room.mtl"):
        assert (tmp_path / f).stat().st_size > 0
    # --mesh glb obj: the room textured with the tilted input, in the same y-up frame as the wireframe .obj
    doc, _ = read_glb(tmp_path / "tilt_room.glb")
    assert doc["images"] and doc["meshes"] and all(p.exists() for p in files)
    assert {p.name for p in files} >= {"tilt_room.glb", "tilt_room.obj", "tilt_room.mtl"}
