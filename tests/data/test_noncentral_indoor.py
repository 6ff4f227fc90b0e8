"""NonCentralIndoorDataset loader on files written by the data engine's writer (frame adapter, depth, labels)
and the HorizonNet label_cor format."""

import numpy as np
import pytest
import torch

from omnidl.data.horizonnet_format import (HorizonNetFolderDataset, corners_from_label_cor, read_label_cor,
                                           write_label_cor)
from omnidl.data.noncentral_indoor import NonCentralIndoorDataset, decode_depth, rc_from_name


@pytest.fixture(scope="module")
def engine_sample():
    from omnidl.data.synthetic import SyntheticPanoramaDataset
    ds = SyntheticPanoramaDataset(camera="noncentral_pano", width=128, height=64, rc=1.0, length=1, furniture=False)
    return ds[0]


def test_roundtrip_through_writer(engine_sample, tmp_path):
    from omnidl.synth.export import sample_name, write_sample
    name = sample_name("noncentral", 3, 1.0)
    write_sample(tmp_path, "noncentral", name, engine_sample)
    ds = NonCentralIndoorDataset(tmp_path)
    assert rc_from_name(name) == pytest.approx(1.0) and len(ds) == 1
    s = ds[0]
    n = int(engine_sample["num_walls"])
    # frame adapter: 3D_gt - cam_pose in the dataset frame comes back as the engine's camera-frame corners
    assert torch.allclose(s["corners_cam"], engine_sample["corners_cam"][:n], atol=1e-4)
    v = engine_sample["boundary_valid"] & s["boundary_valid"]
    assert v.float().mean() > 0.9
    assert torch.allclose(s["boundary"][v], engine_sample["boundary"][v], atol=1e-3)
    # depth survives the 24-bit coding (0.6 um steps) where valid
    m = engine_sample["valid"] & (engine_sample["depth"][0] < 10)
    assert torch.allclose(s["depth"][0][m], engine_sample["depth"][0][m], atol=1e-4)
    assert s["meta"]["rig_radius"] == 1.0 and s["corner_heat"].shape == (1, 128)
    # the 'corners' source computes the same boundaries through the camera
    s2 = NonCentralIndoorDataset(tmp_path, boundary_source="corners")[0]
    v2 = v & s2["boundary_valid"]
    assert torch.allclose(s2["boundary"][v2], engine_sample["boundary"][v2], atol=2e-3)
    s3 = NonCentralIndoorDataset(tmp_path, boundary_source="edges")[0]
    assert (s3["boundary"][s3["boundary_valid"]] - engine_sample["boundary"][s3["boundary_valid"]]).abs().median() < 2


def test_rc_errors_and_depth_decoding(tmp_path):
    assert rc_from_name("A23_R06585") == pytest.approx(0.6585) and rc_from_name("AFimg0241") is None
    rgb = np.array([[[25, 128, 3]]], np.uint8)
    assert decode_depth(rgb)[0, 0] == pytest.approx((25 / 255 + 128 / 255 ** 2 + 3 / 255 ** 3) * 10, rel=1e-6)
    (tmp_path / "img").mkdir()
    import cv2
    cv2.imwrite(str(tmp_path / "img" / "AFimg0001.png"), np.zeros((8, 16, 3), np.uint8))
    with pytest.raises(ValueError, match="rig radius"):
        NonCentralIndoorDataset(tmp_path, depth=False)[0]
    with pytest.raises(FileNotFoundError):
        NonCentralIndoorDataset(tmp_path / "nope")


def test_label_cor_format_and_central_folder(tmp_path):
    cor = np.array([[158, 186], [158, 329], [353, 185], [353, 330], [594, 154], [594, 363], [965, 150],
                    [965, 367]], float) / 2
    write_label_cor(tmp_path / "label_cor" / "p.txt", cor)
    assert np.allclose(read_label_cor(tmp_path / "label_cor" / "p.txt"), cor)
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    with pytest.raises(ValueError, match="bad.txt:1"):
        read_label_cor(tmp_path / "bad.txt")
    cc = corners_from_label_cor(cor, 512, 256)
    assert cc.shape == (4, 2, 3) and np.allclose(cc[:, 1, 1], 1.6)       # floor 1.6 m below (camera y down)
    import cv2
    (tmp_path / "img").mkdir()
    cv2.imwrite(str(tmp_path / "img" / "p.png"), np.zeros((256, 512, 3), np.uint8))
    s = HorizonNetFolderDataset(tmp_path)[0]
    # the boundary at each corner column passes through the labelled corner rows (central camera)
    for x, y in cor:
        j = int(round(x))
        assert abs(float(s["boundary"][0 if y < 128 else 1, j]) - (y + 0.5)) < 3
