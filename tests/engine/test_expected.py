"""End-of-run lines with the expected range; periodic validation/checkpoints by wall time."""
import json
from pathlib import Path

from omegaconf import OmegaConf

from omnidl.engine import train
from omnidl.engine.expected import expected_ranges, summary_lines


def _cfg(seed=0):
    return OmegaConf.create({"trainer": {"seed": seed}, "model": {"name": "fredsnet"},
                             "expected": {"when": {"model.name": "fredsnet", "trainer.seed": 0}, "seeds": "seed 0",
                                          "metrics": {"val/delta1": [0.2, 0.4], "val/miou": [0.1, 0.2]}}})


def test_summary_lines_show_the_expected_range_only_for_the_default_run():
    final = {"val/loss": 3.0, "val/loss_depth": 1.0, "val/delta1": 0.3, "val/miou": 0.05}
    lines = summary_lines(final, _cfg())
    assert "expected range of this default run (seed 0)" in lines[0]
    assert any("val/delta1" in x and "expected [0.2, 0.4]" in x and "OUTSIDE" not in x for x in lines)
    assert any("val/miou" in x and "OUTSIDE" in x for x in lines)
    assert not any("val/loss_depth" in x for x in lines)
    assert expected_ranges(_cfg(seed=1)) is None
    assert "expected" not in " ".join(summary_lines(final, _cfg(seed=1)))


def _losses(out: Path):
    return {r["step"]: r["loss"] for r in map(json.loads, (out / "train_log.jsonl").read_text().splitlines())}


def test_wall_time_validation_and_checkpoints_do_not_change_training(cfg_factory, caplog):
    base = ["trainer.max_steps=6", "trainer.batch_size=2", "trainer.log_every_steps=1", "trainer.tensorboard=false",
            "trainer.val_every_minutes=0", "trainer.ckpt_every_minutes=0"]
    ref = train(cfg_factory(base, sub="ref"))
    with caplog.at_level("INFO", logger="omnidl.engine"):
        timed = train(cfg_factory(base + ["trainer.val_every_minutes=1e-9", "trainer.ckpt_every_minutes=1e-9"],
                                  sub="timed"))
    assert caplog.text.count("validation:") == 6  # every step, by wall time
    assert _losses(Path(timed["output_dir"])) == _losses(Path(ref["output_dir"]))


def test_ranges_from_runs_cover_every_run(tmp_path, capsys):
    from omnidl.engine.expected import main, ranges_from_runs
    finals = [{"val/delta1": 0.30, "val/loss_x": 1.0}, {"val/delta1": 0.34}]
    r = ranges_from_runs(finals)
    assert list(r) == ["val/delta1"] and r["val/delta1"][0] < 0.30 and r["val/delta1"][1] > 0.34
    for i, f in enumerate(finals):
        (tmp_path / str(i)).mkdir()
        (tmp_path / str(i) / "metrics.json").write_text(json.dumps({"final": f}))
    assert main([str(tmp_path / "0"), str(tmp_path / "1")]) == 0 and "val/delta1: [" in capsys.readouterr().out
    assert main([str(tmp_path / "missing")]) == 2
