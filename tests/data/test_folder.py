import cv2
import numpy as np
import pytest

from .data_fixtures import truncate
from omnidl.data.folder import ImageFolder
from omnidl.data.robust import CorruptSampleError


def test_folder_lists_images_and_resizes(tmp_path):
    for i, ext in enumerate([".png", ".jpg"]):
        cv2.imwrite(str(tmp_path / f"p{i}{ext}"), np.full((40, 80, 3), 100 + i, np.uint8))
    (tmp_path / "notes.txt").write_text("x")
    ds = ImageFolder(str(tmp_path), height=16, width=32)
    assert len(ds) == 2
    s = ds[0]
    assert set(s) == {"image", "meta"} and s["image"].shape == (3, 16, 32)
    assert abs(float(s["image"].mean()) - 100 / 255) < 1e-6
    assert s["meta"]["name"] == "p0"


def test_folder_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        ImageFolder(str(tmp_path / "missing"))
    with pytest.raises(FileNotFoundError, match="no images"):
        ImageFolder(str(tmp_path))
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((8, 16, 3), np.uint8))
    truncate(tmp_path / "a.png", 0.6)
    with pytest.raises(CorruptSampleError, match="a.png"):
        ImageFolder(str(tmp_path))[0]
