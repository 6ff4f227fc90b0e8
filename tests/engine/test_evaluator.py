import csv
import json
import logging
import os
import re
import sys
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


# --- output names: every sample keeps its own files (issue 14: sanitised names overwrote each other) ---------

def test_output_names_are_unique_safe_and_stable():
    from omnidl.engine.eval_outputs import OutputNames, printable

    bad1, bad2 = os.fsdecode(b"room\xff"), os.fsdecode(b"room\xfe")   # two non-UTF-8 file names
    names = ["a b", "a?b", "a_b", "x/y", "x_y", bad1, bad2, "A_B", ".hidden", "", "a" * 300, "sample_000"]
    make = OutputNames()
    stems = [make(n) for n in names]
    assert len({s.lower() for s in stems}) == len(names)                     # no two share a file
    assert all(re.fullmatch(r"[\w.-]+", s) and not s.startswith(".") and len(s) <= 140 for s in stems)
    assert stems[2] == "a_b" and stems[-1] == "sample_000"                  # safe names stay as they are
    assert stems[0].startswith("a_b-") and stems[1].startswith("a_b-")
    again = OutputNames()
    assert [again(n) for n in names] == stems                               # the same stems in every run
    assert OutputNames()("a?b") == stems[1]                                 # ...whatever else is in the folder
    assert printable(bad1) == "room\\xff"
    # the same name twice (two files in different folders) is told apart by the source file
    same = OutputNames()
    assert same("pano", "/d1/pano.png") == "pano" and same("pano", "/d2/pano.png").startswith("pano-")


def _folder(root, files):
    for i, rel in enumerate(files):
        p = root / os.fsdecode(rel)
        p.parent.mkdir(parents=True, exist_ok=True)
        ok, buf = cv2.imencode(".png", np.full((20, 40, 3), 40 * i + 10, np.uint8))
        p.write_bytes(buf.tobytes())


def test_names_that_sanitise_alike_keep_every_output(cfg_factory, trained, tmp_path):
    files = ["a b.png", "a?b.png", "a_b.png", "x/y.png", "x_y.png"]
    _folder(tmp_path / "mine", files)
    cfg = cfg_factory([f"checkpoint={trained}", "data=folder", f"data.root={tmp_path / 'mine'}", "data.recursive=true",
                       "data.height=16", "data.width=32", "eval.save_images=-1", "eval.save_pointclouds=-1"],
                      config_name="evaluate", sub="collide")
    res = evaluate(cfg)
    out = Path(cfg.paths.output_dir)
    rows = list(csv.DictReader(open(out / "per_image.csv", encoding="utf-8")))
    assert res["num_images"] == 5 and len({r["output"] for r in rows}) == 5
    assert {r["name"] for r in rows} >= {"a b", "a?b", "a_b", "x/y", "x_y"}        # the original names are kept
    for kind, suffix in (("images", ".png"), ("pointclouds", ".ply"), ("predictions", "_depth.png")):
        assert sorted(p.name for p in (out / kind).glob(f"*{suffix}")) == sorted(r["output"] + suffix for r in rows)
    # each picture is its own image's (the inputs have different grey levels)
    firsts = {tuple(cv2.imread(str(out / "images" / f"{r['output']}.png"))[8, 8]) for r in rows}
    assert len(firsts) == 5


@pytest.mark.skipif(sys.platform == "darwin", reason="macOS file systems refuse non-UTF-8 names")
def test_non_utf8_names_keep_every_output(cfg_factory, trained, tmp_path):
    _folder(tmp_path / "mine", [b"room\xff.png", b"room\xfe.png"])
    cfg = cfg_factory([f"checkpoint={trained}", "data=folder", f"data.root={tmp_path / 'mine'}", "data.height=16",
                       "data.width=32", "eval.save_pointclouds=0"], config_name="evaluate", sub="bytes")
    evaluate(cfg)
    out = Path(cfg.paths.output_dir)
    rows = list(csv.DictReader(open(out / "per_image.csv", encoding="utf-8")))
    assert sorted(r["name"] for r in rows) == ["room\\xfe", "room\\xff"]
    assert len(list((out / "images").iterdir())) == 2 and len({r["output"] for r in rows}) == 2


def test_folder_runs_at_the_checkpoints_training_size(cfg_factory, trained, tmp_path, caplog):
    ckpt = torch.load(trained, weights_only=False)
    ckpt["config"]["data"].update(height=16, width=32)                       # what a real training config stores
    sized = tmp_path / "sized.pt"
    torch.save(ckpt, sized)
    _folder(tmp_path / "mine", ["p.png"])                                    # 40x20 files, no size given
    cfg = cfg_factory([f"checkpoint={sized}", "data=folder", f"data.root={tmp_path / 'mine'}"],
                      config_name="evaluate", sub="size")
    assert cfg.data.height is None and cfg.data.width is None
    with caplog.at_level(logging.INFO, logger="omnidl"):
        evaluate(cfg)
    out = Path(cfg.paths.output_dir)
    assert cv2.imread(str(out / "predictions" / "p_semantic.png"), cv2.IMREAD_UNCHANGED).shape == (16, 32)
    assert "input size 32x16: the checkpoint's training size" in caplog.text


def test_log_names_the_loaded_weights_not_random_initialisation(cfg_factory, trained, caplog):
    import omnidl.engine.evaluator as ev

    built = []

    def build_with_backbone_note(cfg):                                      # a model whose build logs the note
        logging.getLogger("omnidl.models._backbone").info("backbone resnet18: random initialisation (set ...)")
        built.append(1)
        return real_build(cfg)

    real_build = ev.build_model
    cfg = cfg_factory([f"checkpoint={trained}", "eval.save_images=0", "eval.save_pointclouds=0"],
                      config_name="evaluate", sub="weights")
    with caplog.at_level(logging.INFO):
        ev.build_model = build_with_backbone_note
        try:
            evaluate(cfg)
        finally:
            ev.build_model = real_build
    assert built and "random initialisation" not in caplog.text
    assert re.search(rf"loaded all weights from {re.escape(str(trained))} \(step 3, .*values\)", caplog.text)


def test_full_resolution_titled_figures_inputs_and_upright_clouds(cfg_factory, trained):
    from omnidl.viz import ply_frame

    cfg = cfg_factory([f"checkpoint={trained}", "eval.save_images=1", "eval.save_pointclouds=1"],
                      config_name="evaluate", sub="fullres")
    with open_dict(cfg):
        cfg.data.test.update(height=64, width=128)
    evaluate(cfg)
    out = Path(cfg.paths.output_dir)
    pic = cv2.imread(str(out / "images" / "sample_000.png"))
    # five 128-px panels side by side, titles above them and the colour bar / legend key beside them
    assert pic.shape[0] > 64 and pic.shape[1] > 5 * 128
    assert cv2.imread(str(out / "inputs" / "sample_000.jpg")).shape == (64, 128, 3)
    pts, _ = read_ply(out / "pointclouds" / "sample_000.ply")
    assert ply_frame(out / "pointclouds" / "sample_000.ply") == "gravity_y_up" and pts.shape == (64 * 128, 3)


def test_rotation_plot_has_one_panel_per_unit(tmp_path):
    from omnidl.engine.eval_outputs import write_rotation

    write_rotation(tmp_path, {"0": {"mae": 1.0, "acc": 0.5}, "10": {"mae": 1.2, "acc": 0.4}})
    assert cv2.imread(str(tmp_path / "rotation.png")).shape[0] == 2 * 320      # metres panel + fraction panel
    write_rotation(tmp_path, {"0": {"acc": 0.5}, "10": {"acc": 0.4}})
    assert cv2.imread(str(tmp_path / "rotation.png")).shape[0] == 320
