"""OpenCV's camera-calibration tutorial output (samples/cpp/tutorial_code/calib3d/camera_calibration).

The tutorial's sample ``out_camera_data.yml`` and its documentation's XML use ``Camera_Matrix``,
``Distortion_Coefficients``, ``image_Width`` and ``image_Height``; the current sample program writes
``camera_matrix``, ``distortion_coefficients``, ``image_width``, ``image_height`` and the ``fisheye_model``
flag. The fixtures are written in those layouts (shortened: per-view errors, extrinsics and image points
left out where noted).
"""
import cv2
import numpy as np
import pytest
import torch

from omnidl.cameras import KannalaBrandt
from omnidl.cameras.io import detect_format, load, save

#: the tutorial's sample output out_camera_data.yml (its first nodes; the per-view data is cut)
TUTORIAL_YML = """%YAML:1.0
calibration_Time: "08/19/11 20:44:38"
nrOfFrames: 8
image_Width: 640
image_Height: 480
board_Width: 9
board_Height: 6
square_Size: 50.
FixAspectRatio: 1.
# flags:  +fix_aspectRatio +fix_principal_point +zero_tangent_dist
flagValue: 14
Camera_Matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 6.5746697810243404e+002, 0., 3.1950000000000000e+002, 0.,
       6.5746697810243404e+002, 2.3950000000000000e+002, 0., 0., 1. ]
Distortion_Coefficients: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ -4.1802327018241026e-001, 5.0715243805833121e-001, 0., 0.,
       -5.7843596847939704e-001 ]
Avg_Reprojection_Error: 3.8441346462381665e-001
Per_View_Reprojection_Errors: !!opencv-matrix
   rows: 2
   cols: 1
   dt: f
   data: [ 5.04357755e-001, 4.85754758e-001 ]
"""

#: the same calibration as the tutorial's documentation shows it in XML
TUTORIAL_XML = """<?xml version="1.0"?>
<opencv_storage>
<calibration_Time>"07/18/11 20:39:26"</calibration_Time>
<nrOfFrames>5</nrOfFrames>
<image_Width>640</image_Width>
<image_Height>480</image_Height>
<board_Width>9</board_Width>
<board_Height>6</board_Height>
<square_Size>50.</square_Size>
<FixAspectRatio>1.</FixAspectRatio>
<!-- flags:  +fix_aspectRatio +fix_principal_point +zero_tangent_dist -->
<flagValue>14</flagValue>
<Camera_Matrix type_id="opencv-matrix">
  <rows>3</rows>
  <cols>3</cols>
  <dt>d</dt>
  <data>
    6.5746697944293521e+002 0. 3.1950000000000000e+002 0.
    6.5746697944293521e+002 2.3950000000000000e+002 0. 0. 1.</data></Camera_Matrix>
<Distortion_Coefficients type_id="opencv-matrix">
  <rows>5</rows>
  <cols>1</cols>
  <dt>d</dt>
  <data>
    -4.1802327176423804e-001 5.0715244063187526e-001 0. 0.
    -5.7843597214487474e-001</data></Distortion_Coefficients>
<Avg_Reprojection_Error>3.9403000707029748e-001</Avg_Reprojection_Error>
</opencv_storage>
"""

#: the current tutorial program with the fisheye model (calibration_time ... fisheye_model: 1, D of 4 values)
TUTORIAL_FISHEYE = """%YAML:1.0
---
calibration_time: "Mon Jan  6 10:00:00 2025"
nr_of_frames: 25
image_width: 1280
image_height: 960
board_width: 9
board_height: 6
square_size: 25.
flags: 0
fisheye_model: 1
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 3.4e+02, 0., 6.395e+02, 0., 3.41e+02, 4.795e+02, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 4
   cols: 1
   dt: d
   data: [ 5.0e-02, -1.0e-02, 2.0e-03, -1.0e-04 ]
avg_reprojection_error: 3.1e-01
"""


@pytest.mark.parametrize("name,text", [("out_camera_data.yml", TUTORIAL_YML), ("out_camera_data.xml", TUTORIAL_XML)])
def test_tutorial_output_keys_are_recognised(tmp_path, name, text):
    # regression: "format not recognised" (Camera_Matrix / image_Width were unknown keys)
    path = tmp_path / name
    path.write_text(text)
    assert detect_format(path) == "opencv"
    cam = load(path)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)  # the fixture is what OpenCV itself reads
    K, D = fs.getNode("Camera_Matrix").mat(), fs.getNode("Distortion_Coefficients").mat().ravel()
    assert type(cam).name == "opencv" and (cam.width, cam.height) == (640, 480)
    assert (cam.fx, cam.cx, cam.cy) == (K[0, 0], K[0, 2] + 0.5, K[1, 2] + 0.5)
    assert (cam.k1, cam.k2, cam.p1, cam.p2, cam.k3) == tuple(D)
    pts = np.array([[0.1, -0.2, 1.0], [0.3, 0.25, 1.0], [-0.35, 0.1, 1.0]])
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, D)
    uv, _ = cam.project(torch.from_numpy(pts))
    assert np.abs(uv.numpy() - 0.5 - ref.reshape(-1, 2)).max() < 1e-6


def test_tutorial_fisheye_flag(tmp_path):
    path = tmp_path / "out_camera_data.yml"
    path.write_text(TUTORIAL_FISHEYE)
    cam = load(path)
    assert isinstance(cam, KannalaBrandt) and (cam.k1, cam.k4, cam.cx) == (0.05, -1e-4, 640.0)
    # the flag decides, also against the D-of-4 guess: fisheye_model 0 with 4 coefficients is calibrateCamera's
    flat = tmp_path / "flat.yml"
    flat.write_text(TUTORIAL_FISHEYE.replace("fisheye_model: 1", "fisheye_model: 0")
                    .replace("distortion_coefficients:", "D:"))
    assert type(load(flat)).name == "opencv"
    bad = tmp_path / "bad.yml"
    bad.write_text(TUTORIAL_FISHEYE.replace("fisheye_model: 1", "fisheye_model: 7"))
    with pytest.raises(ValueError, match=r"fisheye_model must be 0 or 1.*got 7"):
        load(bad)
    # written back in the current tutorial's names, with the flag, read back identical
    out = save(cam, tmp_path / "again.yml", format="opencv")
    assert "fisheye_model: 1" in out.read_text() and load(out) == cam
