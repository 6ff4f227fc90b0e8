import logging

import cv2
import numpy as np
import pytest
import torch

from .data_fixtures import S2D3DS_CLASSES, truncate, write_stanford
from omnidl.data.collate import collate_samples
from omnidl.data.robust import CorruptSampleError, SkipCorrupt
from omnidl.data.stanford2d3ds import FOLDS, Stanford2D3DS, label_lut


def test_decodes_rgb_depth_semantic_exactly(tmp_path):
    truth = write_stanford(tmp_path)
    ds = Stanford2D3DS(str(tmp_path), areas=["1"], height=None, width=None)
    assert len(ds) == 2 and all(s.name.startswith("area_1_") for s in ds.samples)
    s = ds[0]
    rgb, depth_m, index = truth[s["meta"]["name"]]
    assert s["image"].shape == (3, 32, 64) and s["image"].dtype == torch.float32
    assert torch.allclose(s["image"], torch.from_numpy(rgb).permute(2, 0, 1).float() / 255)
    assert torch.allclose(s["depth"][0].double(), torch.from_numpy(depth_m), atol=1e-6)
    assert s["depth"][0, 0, :5].eq(0).all()  # 65535 -> invalid
    lut = np.array(S2D3DS_CLASSES)
    expect = np.where(index < len(lut), lut[np.minimum(index, len(lut) - 1)], 0)
    assert torch.equal(s["semantic"], torch.from_numpy(expect))
    assert s["semantic"][1, :3].eq(0).all()  # #0D0D0D -> unknown


def test_fold1_test_is_area5_and_resize(tmp_path):
    write_stanford(tmp_path, areas=("1", "5a", "5b"), per_area=1)
    ds = Stanford2D3DS(str(tmp_path), split="test", height=16, width=32)
    assert {s.name[:8] for s in ds.samples} == {"area_5a_", "area_5b_"}
    s = ds[0]
    assert s["image"].shape == (3, 16, 32) and s["depth"].shape == (1, 16, 32) and s["semantic"].shape == (16, 32)
    assert FOLDS[1] == (("1", "2", "3", "4", "6"), ("5a", "5b"))


def test_label_json_maps_by_class_name(tmp_path):
    p = tmp_path / "l.json"
    p.write_text('["<UNK>_0_<UNK>_0_0", "sofa_2_lounge_1_1", "bookcase_1_x_1_1", "mystery_1_x_1_1"]')
    assert label_lut(p).tolist() == [0, 10, 3, 0]


def test_missing_folder_named(tmp_path):
    write_stanford(tmp_path, areas=("1",), per_area=1)
    with pytest.raises(FileNotFoundError, match=r"area_2/pano/rgb"):
        Stanford2D3DS(str(tmp_path), split="train")  # fold 1 needs areas 1,2,3,4,6
    with pytest.raises(FileNotFoundError, match="does not exist"):
        Stanford2D3DS(str(tmp_path / "nope"), areas=["1"])
    (tmp_path / "assets" / "semantic_labels.json").unlink()
    with pytest.raises(FileNotFoundError, match="semantic_labels.json"):
        Stanford2D3DS(str(tmp_path), areas=["1"])


def test_missing_label_file_skipped_with_warning(tmp_path, caplog):
    write_stanford(tmp_path, areas=("1",), per_area=2)
    victim = sorted((tmp_path / "area_1/pano/semantic").glob("*.png"))[0]
    victim.unlink()
    with caplog.at_level(logging.WARNING, logger="omnidl.data"):
        ds = Stanford2D3DS(str(tmp_path), areas=["1"])
    assert len(ds) == 1
    assert str(victim) in caplog.text


def test_truncated_png_and_wrong_size_are_clear_errors(tmp_path, caplog):
    write_stanford(tmp_path, areas=("1",), per_area=3)
    ds = Stanford2D3DS(str(tmp_path), areas=["1"], height=None, width=None)
    truncate(ds.samples[0].image)
    bad_depth = ds.samples[1].depth
    cv2.imwrite(str(bad_depth), np.ones((10, 20), np.uint16))
    with pytest.raises(CorruptSampleError, match="truncated|cannot decode"):
        ds[0]
    with pytest.raises(CorruptSampleError, match=r"20x10, expected 64x32"):
        ds[1]
    robust = SkipCorrupt(ds)
    with caplog.at_level(logging.WARNING, logger="omnidl.data"):
        batch = collate_samples([robust[i] for i in range(3)])
    assert batch["image"].shape[0] == 1  # the two broken samples were dropped
    assert str(ds.samples[0].image) in caplog.text and str(bad_depth) in caplog.text
