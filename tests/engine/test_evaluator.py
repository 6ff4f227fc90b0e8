import csv
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from omegaconf import open_dict

from omnidl.engine import evaluate, train
from omnidl.viz import read_ply


@pytest.fixture
def trained(cfg_factory):
    cfg = cfg_factory(["trainer.max_steps=3", "trainer.tensorboard=false"], sub="train")
    return train(cfg)["checkpoint_best"]


def test_evaluate_writes_metrics_pictures_and_pointclouds(cfg_factory, trained):
    cfg = cfg_factory([f"checkpoint={trained}", "eval.save_images=2", "eval.save_pointclouds=1"],
                      config_name="evaluate", sub="eval")
    res = evaluate(cfg)
    out = Path(cfg.paths.output_dir)
    assert res["num_images"] == 3 and set(res["metrics"]) == {"mae", "acc"}
    assert json.loads((out / "metrics.json").read_text())["metrics"] == res["metrics"]
    rows = list(csv.DictReader(open(out / "per_image.csv")))
    assert [r["name"] for r in rows] == ["sample_000", "sample_001", "sample_002"]
    # every image has the same number of valid depth pixels: the mean of per-image MAE is the dataset MAE
    assert np.mean([float(r["mae"]) for r in rows]) == pytest.approx(res["metrics"]["mae"], rel=1e-6)
    pic = cv2.imread(str(out / "images" / "sample_000.png"))
    assert pic.shape[0] == 16 and pic.shape[1] == 5 * 32 + 4 * 2  # RGB | depth pred | GT | sem pred | GT
    assert sorted(p.name for p in (out / "images").iterdir()) == ["sample_000.png", "sample_001.png"]
    pts, cols = read_ply(out / "pointclouds" / "sample_000.ply")
    assert pts.shape == (16 * 32, 3) and cols.shape == pts.shape
    pred_mm = cv2.imread(str(out / "predictions" / "sample_000_depth.png"), cv2.IMREAD_UNCHANGED)
    # the point cloud's ranges are the predicted depths (camera centre at the origin)
    assert np.allclose(np.sort(np.linalg.norm(pts, axis=1)), np.sort(pred_mm.ravel() / 1000.0), atol=1e-3)


def test_rotation_sweep(cfg_factory, trained):
    cfg = cfg_factory([f"checkpoint={trained}", "eval.rotation_deg=[0,10,20]", "eval.save_images=0",
                       "eval.save_pointclouds=0"], config_name="evaluate", sub="rot")
    res = evaluate(cfg)
    out = Path(cfg.paths.output_dir)
    assert list(res["rotation"]) == ["0", "10", "20"] and res["rotation"]["0"] == res["metrics"]
    assert res["rotation"]["20"] != res["metrics"]
    rows = list(csv.DictReader(open(out / "rotation.csv")))
    assert [float(r["angle_deg"]) for r in rows] == [0, 10, 20]
    assert (out / "rotation.png").stat().st_size > 1000


def test_folder_of_unlabelled_images(cfg_factory, trained, tmp_path):
    imgs = tmp_path / "mine"
    imgs.mkdir()
    for i in range(2):
        cv2.imwrite(str(imgs / f"pano{i}.jpg"), np.full((20, 40, 3), 60 * i, np.uint8))
    cfg = cfg_factory([f"checkpoint={trained}", "data=folder", f"data.root={imgs}", "data.height=16", "data.width=32"],
                      config_name="evaluate", sub="folder")
    res = evaluate(cfg)
    out = Path(cfg.paths.output_dir)
    assert res["num_images"] == 2 and res["metrics"] == {}
    assert (out / "images" / "pano1.png").is_file() and (out / "pointclouds" / "pano0.ply").is_file()
    assert cv2.imread(str(out / "predictions" / "pano0_semantic.png"), cv2.IMREAD_UNCHANGED).shape == (16, 32)


def test_postprocess_hooks_are_run(cfg_factory, trained):
    from omnidl.postprocess.registry import _HOOKS, register_hook

    if "engine_test_mean_depth" not in _HOOKS:
        @register_hook("engine_test_mean_depth")
        def _hook(outputs, batch, scale=1.0):
            return {"mean_depth": float(outputs["depth"].mean()) * scale, "profile": outputs["depth"].mean(-1)[0, 0]}

    cfg = cfg_factory([f"checkpoint={trained}", "postprocess=[engine_test_mean_depth]",
                       "+postprocess_options.engine_test_mean_depth.scale=2.0", "eval.save_images=0",
                       "eval.save_pointclouds=0"], config_name="evaluate", sub="hooks")
    evaluate(cfg)
    out = Path(cfg.paths.output_dir)
    rows = list(csv.DictReader(open(out / "per_image.csv")))
    assert all(float(r["mean_depth"]) > 0 for r in rows)
    lines = (out / "postprocess.jsonl").read_text().splitlines()
    assert len(lines) == 3 and len(json.loads(lines[0])["profile"]) == 16


def test_bad_checkpoint_is_a_clear_error(cfg_factory, tmp_path):
    torch.save({"model": {"nope": torch.zeros(1)}}, tmp_path / "x.pt")
    cfg = cfg_factory([f"checkpoint={tmp_path / 'x.pt'}"], config_name="evaluate", sub="bad")
    with pytest.raises(RuntimeError, match="does not fit the model"):
        evaluate(cfg)


def test_model_and_data_from_the_checkpoint_config(cfg_factory, trained):
    cfg = cfg_factory([f"checkpoint={trained}", "eval.save_images=0", "eval.save_pointclouds=0"],
                      config_name="evaluate", sub="fromckpt", standin=False)
    assert cfg.model is None
    res = evaluate(cfg)
    assert res["num_images"] == 3 and set(res["metrics"]) == {"mae", "acc"}
