import pytest
import torch

from .data_fixtures import write_matterport
from omnidl.data.matterport3d import Matterport3D


def test_depth_is_value_over_4000_and_semantic(tmp_path):
    truth = write_matterport(tmp_path, splits={"train": ["scA"], "test": ["scB"]})
    ds = Matterport3D(str(tmp_path), split="train", height=None, width=None, semantic=True)
    assert len(ds) == 2 and all(s.name.startswith("scA_") for s in ds.samples)
    s = ds[1]
    rgb, depth, sem = truth[s["meta"]["name"]]
    assert torch.allclose(s["depth"][0].double(), torch.from_numpy(depth), atol=1e-6)
    assert torch.equal(s["semantic"], torch.from_numpy(sem).long())
    assert torch.allclose(s["image"], torch.from_numpy(rgb).permute(2, 0, 1).float() / 255)
    assert len(Matterport3D(str(tmp_path), split="test")) == 2


def test_without_split_file_uses_all_scenes_and_no_semantic(tmp_path):
    write_matterport(tmp_path, semantic=False)
    ds = Matterport3D(str(tmp_path), split="val", height=16, width=32)
    assert len(ds) == 4 and "semantic" not in ds[0] and ds[0]["depth"].shape == (1, 16, 32)


def test_missing_scene_named(tmp_path):
    write_matterport(tmp_path, splits={"train": ["scA", "scZ"]})
    with pytest.raises(FileNotFoundError, match="scZ"):
        Matterport3D(str(tmp_path), split="train")
