"""Synthetic datasets: determinism, disjoint splits, cache, collation, camera specs."""
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from omnidl.data.synthetic import SyntheticCameraDataset, SyntheticPanoramaDataset
from omnidl.synth import sample_seeds


@pytest.fixture(autouse=True)
def _threads():
    torch.set_num_threads(1)


def _equal(a, b):
    return all(torch.equal(a[k], b[k]) for k in a if k != "meta")


def test_same_seed_gives_bit_identical_samples():
    a = SyntheticPanoramaDataset("noncentral_pano", 64, 32, rc=0.5, length=4, seed=7)
    b = SyntheticPanoramaDataset("noncentral_pano", 64, 32, rc=0.5, length=4, seed=7)
    assert _equal(a[2], b[2])
    assert a[2]["meta"]["split"] == "train" and a[2]["meta"]["index"] == 2
    c = SyntheticPanoramaDataset("noncentral_pano", 64, 32, rc=0.5, length=4, seed=8)
    assert not torch.equal(a[2]["image"], c[2]["image"])


def test_splits_use_disjoint_seeds():
    seeds = {s: {sample_seeds(0, s, i)[0] for i in range(500)} for s in ("train", "val", "test")}
    assert not (seeds["train"] & seeds["val"]) and not (seeds["train"] & seeds["test"])
    assert not (seeds["val"] & seeds["test"])
    tr = SyntheticPanoramaDataset("equirect", 64, 32, length=2, split="train")
    te = SyntheticPanoramaDataset("equirect", 64, 32, length=2, split="test")
    assert not torch.equal(tr[0]["image"], te[0]["image"])


def test_sample_dict_shapes_and_collation():
    ds = SyntheticPanoramaDataset("equirect", 64, 32, length=4)
    s = ds[0]
    assert s["image"].shape == (3, 32, 64) and s["image"].dtype == torch.float32
    assert s["depth"].shape == (1, 32, 64) and s["semantic"].dtype == torch.int64
    assert s["boundary"].shape == (2, 64) and s["corners_uv"].shape == (14, 2, 2)
    batch = next(iter(DataLoader(ds, batch_size=2, collate_fn=_collate)))
    assert batch["image"].shape == (2, 3, 32, 64) and batch["lines_cam"].shape == (2, 14, 2, 6)


def _collate(items):
    from torch.utils.data import default_collate
    meta = [i.pop("meta") for i in items]
    out = default_collate(items)
    out["meta"] = meta
    return out


def test_cache_roundtrip(tmp_path):
    ds = SyntheticPanoramaDataset("equirect", 64, 32, length=2, cache_dir=tmp_path)
    first = ds[1]
    files = list(tmp_path.rglob("*.pt"))
    assert len(files) == 1 and not list(tmp_path.rglob("*.tmp"))
    again = SyntheticPanoramaDataset("equirect", 64, 32, length=2, cache_dir=tmp_path)[1]
    assert _equal(first, again)
    other = SyntheticPanoramaDataset("equirect", 64, 32, length=2, cache_dir=tmp_path, seed=1)
    other[1]
    assert len(list(tmp_path.rglob("*.pt"))) == 2   # options change the cache key


def test_generic_camera_dataset_and_errors(tmp_path):
    ds = SyntheticCameraDataset("fisheye_equiangular", width=48, height=48, length=2, rotation="random")
    s = ds[0]
    assert s["image"].shape == (3, 48, 48) and (~s["valid"]).any()
    assert not torch.allclose(s["rotation"], torch.eye(3))
    with pytest.raises(ValueError, match="split"):
        SyntheticPanoramaDataset("equirect", 64, 32, split="dev")
    with pytest.raises(ValueError, match="noncentral_pano"):
        SyntheticPanoramaDataset("fisheye", 64, 32)
    with pytest.raises(ValueError, match="unknown camera"):
        SyntheticCameraDataset("no_such_camera")
    with pytest.raises(IndexError):
        SyntheticPanoramaDataset("equirect", 64, 32, length=1)[1]
    bad = tmp_path / "bad.yaml"
    bad.write_text("width: 10\n")
    with pytest.raises(ValueError, match="type"):
        SyntheticCameraDataset(str(bad))
    tilt = np.array([[1, 0, 0], [0, np.cos(0.2), -np.sin(0.2)], [0, np.sin(0.2), np.cos(0.2)]])
    s = SyntheticPanoramaDataset("equirect", 64, 32, length=1, rotation=tilt)[0]
    assert torch.allclose(s["rotation"].double(), torch.as_tensor(tilt), atol=1e-6)


class _Payload:
    """An object whose unpickling would run code (writes a flag file)."""

    def __init__(self, flag):
        self.flag = str(flag)

    def __reduce__(self):
        return (exec, (f"open({self.flag!r}, 'w').write('ran')",))


def test_cache_never_unpickles_code(tmp_path):
    """issue 14: the cache is read with torch.load(weights_only=True): a planted .pt file cannot run code; it is
    re-rendered instead, and a genuine cached sample still loads."""
    ds = SyntheticPanoramaDataset("equirect", 32, 16, length=1, cache_dir=tmp_path / "c")
    fresh = ds[0]
    (cached,) = list((tmp_path / "c").rglob("*.pt"))
    assert _equal(torch.load(cached, weights_only=True), fresh)
    flag = tmp_path / "flag.txt"
    torch.save({"image": _Payload(flag)}, cached)
    again = SyntheticPanoramaDataset("equirect", 32, 16, length=1, cache_dir=tmp_path / "c")[0]
    assert not flag.exists() and _equal(again, fresh)
