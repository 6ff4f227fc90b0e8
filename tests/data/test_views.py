"""Training views of the view chain (omnidl.data.views.PanoramaViews) and the view re-projection ablation config
(configs/experiment/fredsnet_dinov2_views.yaml).

The views' targets are checked against omnidl.synth rendering the room directly through each view's pinhole camera
(its z-depth, colours and labels), and against the chain itself: the views' z-depth fed back through
depth_through_views gives the panorama's range. One training step (the plain network on views, plain state-dict
keys) and one panorama evaluation (the same weights wrapped in ThroughViews by data.through_views) run from the
experiment config, in-process, at the smallest sizes."""
from __future__ import annotations

import math

import pytest
import torch

from omnidl.data.synthetic import SyntheticPanoramaDataset
from omnidl.data.views import PanoramaViews
from omnidl.geometry.views import depth_through_views, view_cos
from omnidl.synth import place_camera, render, sample_room, sample_seeds


@pytest.fixture(scope="module")
def equirect_views():
    src = SyntheticPanoramaDataset(camera="equirect", width=256, height=128, length=1, split="test", layout=False)
    return src, PanoramaViews(src, layout="tangent", size=64, split="test")


def _room(camera, index: int):
    room_seed, cam_seed = sample_seeds(0, "test", index, 0)
    scene = sample_room(room_seed)
    return scene, place_camera(scene, camera, cam_seed)


def test_view_targets_match_the_renderer_through_the_views_pinhole(equirect_views):
    """z-depth of every view = the renderer's z-depth through the view's own pinhole at the panorama's pose:
    median relative error 0.44 % (nearest resampling of a 256 x 128 panorama into 64 x 64 views of 100 deg; 0.22 %
    from 512 x 256), colours and labels agree."""
    src, ds = equirect_views
    assert len(ds) == 12 and ds.views_per_panorama == 12
    scene, pose = _room(src.camera, 0)
    rels, rgb, same = [], [], []
    for i in range(len(ds)):
        s = ds[i]
        assert s["image"].shape == (3, 64, 64) and s["depth"].shape == (1, 64, 64) and s["valid"].all()
        v = ds.all_views[s["meta"]["view"]]
        torch.testing.assert_close(s["rotation"], v.rotation.float())
        pv = pose.copy()
        pv[:3, :3] = pose[:3, :3] @ v.rotation.numpy()
        r = render(scene, v.camera, pv, layout=False)
        z = r["depth"][0] * view_cos(v, torch.float32)
        ok = r["valid"] & (z > 0)
        rels.append(((s["depth"][0] - z).abs() / z)[ok])
        rgb.append((s["image"] - r["image"]).abs().mean(0)[ok])
        same.append((s["semantic"] == r["semantic"])[ok].float())
    rel, rgb, same = torch.cat(rels), torch.cat(rgb), torch.cat(same)
    print(f"\nview z-depth vs renderer: median {rel.median():.2e}, p90 {rel.quantile(0.9):.2e}, "
          f"> 10 %: {(rel > 0.1).float().mean():.4f}; colour median {rgb.median():.3f}; labels {same.mean():.3f}")
    assert rel.median() < 0.01
    assert (rel > 0.1).float().mean() < 0.01, "depth mixed across edges"
    assert rgb.median() < 0.05
    assert same.mean() > 0.95


def test_the_chain_inverts_the_views_z_depth(equirect_views):
    """The dataset's z-depth views as the network's predictions: the chain (no alignment) returns the range."""
    src, ds = equirect_views
    pano = src[0]
    by_view = {s["meta"]["view"]: s["depth"] for s in (ds[i] for i in range(len(ds)))}
    index = {tuple(v.rotation.flatten().tolist()): i for i, v in enumerate(ds.all_views)}

    def predict(images, views):
        return torch.stack([by_view[index[tuple(v.rotation.flatten().tolist())]] for v in views])

    res = depth_through_views(pano["image"], src.camera, predict, views=ds.all_views, align="none", batch=16)
    gt = pano["depth"][0]
    ok = res.valid[0] & (gt > 0)
    rel = ((res.depth[0] - gt).abs() / gt)[ok]
    assert ok.float().mean() > 0.999
    assert rel.median() < 0.01


def test_noncentral_source_and_errors():
    src = SyntheticPanoramaDataset(camera="noncentral_pano", width=64, height=32, rc=0.3, length=1, layout=False)
    ds = PanoramaViews(src, layout="cube", size=32)
    s = ds[5]
    assert len(ds) == 6 and s["depth"].shape == (1, 32, 32) and s["valid"].float().mean() > 0.99
    assert (s["depth"][0][s["valid"]] > 0).all() and (s["depth"][0][~s["valid"]] == 0).all()
    with pytest.raises(ValueError, match="split"):
        PanoramaViews(src, split="training")
    with pytest.raises(ValueError, match="length=7"):
        PanoramaViews(src, layout="cube", size=32, length=7)
    with pytest.raises(IndexError):
        ds[6]
    no_depth = [{"image": torch.zeros(3, 16, 32)}]
    with pytest.raises(KeyError, match="has no 'depth'"):
        PanoramaViews(no_depth, size=16)[0]
    square = [{"image": torch.zeros(3, 16, 16), "depth": torch.ones(1, 16, 16)}]
    with pytest.raises(ValueError, match="twice as wide as high"):
        PanoramaViews(square, size=16)[0]


TINY_VIT = ["model.encoder.name=null", "model.encoder.freeze=none",
            "+model.encoder.vit={embed_dim:32,depth:4,num_heads:2,img_size:28,layers:[0,1,2,3]}",
            "+model.encoder.channels=[8,16,16,32]", "model.width=0.0625", "model.head_width=64"]
SMALL = ["experiment=fredsnet_dinov2_views", "trainer=debug", "trainer.max_steps=1", "trainer.batch_size=2",
         "trainer.val_max_batches=1", "trainer.device=cpu", "trainer.num_threads=1", "trainer.progress=false",
         "trainer.tensorboard=false", "viz=none", "data.width=64", "data.height=32", "data.view_size=32",
         "data.train_length=1", "data.val_length=1", "data.test_length=1", *TINY_VIT]


def test_experiment_trains_on_views_and_evaluates_on_panoramas(tmp_path, caplog):
    """``train.py experiment=fredsnet_dinov2_views`` (one step of the plain network on 32 x 32 views, a tiny ViT;
    validation on views) writes plain FreDSNet state-dict keys (as ``model.pretrained`` and the sibling ablations
    have them), and ``evaluate.py`` of its checkpoint runs the 64 x 32 test panorama through the chain."""
    from hydra import compose, initialize_config_dir

    from omnidl.engine import evaluate, register_configs, train
    from omnidl.engine.build import build_model
    from omnidl.engine.checkpoint import load_checkpoint
    from omnidl.engine.config import config_root
    register_configs()
    with initialize_config_dir(version_base="1.3", config_dir=str(config_root()), job_name="test_views"):
        cfg = compose(config_name="train", overrides=[f"paths.output_dir={tmp_path / 'run'}", *SMALL])
        ecfg = compose(config_name="evaluate", overrides=[
            f"paths.output_dir={tmp_path / 'eval'}", f"checkpoint={tmp_path / 'run' / 'checkpoints' / 'last.pt'}",
            "eval.save_images=0", "eval.save_pointclouds=0", *SMALL])
    assert cfg.model.name == "fredsnet" and cfg.model.encoder.vit.embed_dim == 32 and cfg.loss.wrap is False
    assert cfg.data.through_views.size == 32 and "pretrained" in cfg.model
    summary = train(cfg)
    assert summary["step"] == 1 and 0 <= summary["final"]["val/delta1"] <= 1      # validation on views
    weights = load_checkpoint(str(tmp_path / "run" / "checkpoints" / "last.pt"))["model"]
    assert not any(k.startswith("net.") for k in weights)
    build_model(cfg).load_state_dict(weights)                                     # strict: the plain keys
    with caplog.at_level("INFO", logger="omnidl.engine"):
        result = evaluate(ecfg)
    assert "through the view chain" in caplog.text
    assert result["num_images"] == 1
    m = result["metrics"]
    assert {"mre", "delta1", "miou"} <= set(m) and not any(math.isnan(v) for v in m.values())  # depth and semantics, no NaN
