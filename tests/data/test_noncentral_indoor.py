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
    assert s["corners_cam"].shape == (32, 2, 3) and int(s["num_walls"]) == n and (s["corners_cam"][n:] == 0).all()
    assert torch.allclose(s["corners_cam"][:n], engine_sample["corners_cam"][:n], atol=1e-4)
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


def test_label_cor_only_mode_matches_the_full_labels(engine_sample, tmp_path):
    """issue 15: image + label_cor only (the other folders absent); with the true camera height the corners
    recovered through the non-central camera are the 3D_gt ones and the boundaries those of label_ang."""
    import shutil
    from omnidl.synth.export import sample_name, write_sample
    name = sample_name("noncentral", 0, 1.0)
    write_sample(tmp_path, "noncentral", name, engine_sample)
    full = NonCentralIndoorDataset(tmp_path)[0]
    height = float(full["corners_cam"][0, 1, 1])                     # floor corners: camera y (down) = height
    for d in ("depth_coded", "EM_gt", "DataPython/3D_gt", "DataPython/cam_pose", "DataPython/label_ang"):
        shutil.rmtree(tmp_path / d)
    with pytest.raises(OSError, match=r"missing file .*depth_coded"):
        NonCentralIndoorDataset(tmp_path)[0]                            # the full mode still needs every file
    ds = NonCentralIndoorDataset(tmp_path, label_cor_only=True, camera_height=height)
    s = ds[0]
    assert "depth" not in s and "edges" not in s and s["image"].shape == full["image"].shape
    assert torch.equal(s["corner_heat"], full["corner_heat"]) and int(s["num_walls"]) == int(full["num_walls"])
    n = int(full["num_walls"])
    got, want = s["corners_cam"][:n].reshape(-1, 3), full["corners_cam"][:n].reshape(-1, 3)
    assert torch.cdist(got, want).min(1).values.max() < 0.05             # same corners (label_cor has 2 decimals)
    v = s["boundary_valid"] & full["boundary_valid"]
    assert v.float().mean() > 0.95 and (s["boundary"][v] - full["boundary"][v]).abs().max() < 0.2
    # a HorizonNet-style root/label_cor/ folder works too
    (tmp_path / "DataPython" / "label_cor").rename(tmp_path / "label_cor")
    assert torch.equal(NonCentralIndoorDataset(tmp_path, label_cor_only=True, camera_height=height)[0]["corner_heat"],
                       s["corner_heat"])


def test_skip_corrupt_counts_every_skip_and_whole_passes(tmp_path):
    """SkipCorrupt: None + a warning per skip (unchanged), but every occurrence counts towards max_skips and a
    whole pass of corrupt samples stops with an error naming the files (it looped forever before)."""
    from omnidl.data.robust import CorruptSampleError, SkipCorrupt, TooManyCorruptSamples

    class Items(torch.utils.data.Dataset):
        def __init__(self, bad):
            self.bad = bad

        def __len__(self):
            return 4

        def __getitem__(self, i):
            if i in self.bad:
                raise CorruptSampleError(f"cannot decode image f{i}.png")
            return {"i": i}

    healthy = SkipCorrupt(Items({1}), max_skips=5)             # one bad file, read for many epochs: goes on
    for _ in range(10):
        assert [healthy[i] for i in range(4)] == [{"i": 0}, None, {"i": 2}, {"i": 3}]
    assert healthy.skip_count == 10 and healthy.skipped == {1}
    mostly = SkipCorrupt(Items({1, 2, 3}), max_skips=5)        # 3 distinct bad files never reached max_skips before
    assert [mostly[i] for i in range(4)] == [{"i": 0}, None, None, None]
    assert [mostly[i] for i in range(3)] == [{"i": 0}, None, None]
    with pytest.raises(TooManyCorruptSamples, match=r"6 corrupt samples skipped \(max_skips=5\) against 2 good"):
        mostly[3]
    every = SkipCorrupt(Items({0, 1, 2, 3}))
    assert [every[i] for i in range(3)] == [None, None, None]
    with pytest.raises(TooManyCorruptSamples, match=r"all 4 samples read in a row.*f3\.png"):
        every[3]


def test_splits_size_check_and_padding(engine_sample, tmp_path):
    """Split lists (root/split/<split>.txt, split_file), a listed name without an image, the size check and the
    corners_cam padding (max_walls)."""
    from omnidl.synth.export import sample_name, write_sample
    names = [sample_name("noncentral", i, 1.0) for i in range(3)]
    for n in names:
        write_sample(tmp_path, "noncentral", n, engine_sample)
    (tmp_path / "split").mkdir()
    (tmp_path / "split" / "val.txt").write_text(f"{names[2]}\n# a comment\n{names[0]}\n")
    ds = NonCentralIndoorDataset(tmp_path, split="val", depth=False)
    assert ds.names == [names[2], names[0]] and ds.root == tmp_path
    assert NonCentralIndoorDataset(tmp_path, split="val", max_samples=1).names == [names[2]]
    one = tmp_path / "one.txt"
    one.write_text(names[1] + "\n")
    assert NonCentralIndoorDataset(tmp_path, split="val", split_file=one).names == [names[1]]
    with pytest.raises(FileNotFoundError, match=r"no split file for split 'test'.*split/test\.txt"):
        NonCentralIndoorDataset(tmp_path, split="test")
    one.write_text("SYN09999_R10000\n")
    with pytest.raises(FileNotFoundError, match=r"1 listed name\(s\) have no image .*\['SYN09999_R10000'\]"):
        NonCentralIndoorDataset(tmp_path, split_file=one)
    with pytest.raises(ValueError, match=r"img/SYN00000_R10000\.png: image is 128x64, expected 256x128"):
        NonCentralIndoorDataset(tmp_path, width=256, height=128)[0]
    n = int(engine_sample["num_walls"])
    s = NonCentralIndoorDataset(tmp_path, width=128, height=64, max_walls=n)[0]
    assert s["corners_cam"].shape == (n, 2, 3)
    with pytest.raises(ValueError, match=rf"3D_gt/SYN00000_R10000\.npy: room polygon has {n} corners, more than "
                                         rf"max_walls={n - 1}"):
        NonCentralIndoorDataset(tmp_path, max_walls=n - 1)[0]
