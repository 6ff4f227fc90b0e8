"""Real processes: Ctrl-C/SIGTERM write last.pt and print the resume command; a kill -9 storm never leaves a
missing or corrupt best.pt/last.pt; resume without a run folder is a clear error. (Subprocesses: slow.)"""
import json
import os
import random
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from omnidl.engine import train
from omnidl.engine.checkpoint import load_checkpoint

DRIVER = Path(__file__).resolve().parent / "train_driver.py"
RUN = ["trainer.batch_size=2", "trainer.log_every_steps=1", "trainer.tensorboard=false", "trainer.progress=false",
       "trainer.num_threads=1", "optim.lr=0.01"]


def _env(**extra):
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    env.update({k: str(v) for k, v in extra.items()})
    return env


def _losses(out: Path) -> dict[int, float]:
    return {r["step"]: r["loss"] for r in map(json.loads, (out / "train_log.jsonl").read_text().splitlines())}


def _wait_for_records(path: Path, n: int, proc: subprocess.Popen, timeout: float = 300) -> None:
    t0 = time.time()
    while time.time() - t0 < timeout and proc.poll() is None:
        if path.is_file() and len(path.read_text().splitlines()) >= n:
            return
        time.sleep(0.05)
    raise AssertionError(f"{path} did not get {n} records (process rc {proc.poll()})")


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_writes_last_and_prints_a_resume_command_that_continues_exactly(tmp_path, cfg_factory, sig):
    over = RUN + ["trainer.max_steps=10", "trainer.val_every_steps=5", "trainer.ckpt_every_steps=0",
                  "trainer.ckpt_every_minutes=0", "trainer.val_every_minutes=0"]
    ref = train(cfg_factory(over, sub="ref"))
    run_dir = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, str(DRIVER), *over, f"hydra.run.dir={run_dir}"], cwd=tmp_path,
                            env=_env(OMNIDL_TEST_STEP_SLEEP=0.3), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    _wait_for_records(run_dir / "train_log.jsonl", 3, proc)
    proc.send_signal(sig)
    text, _ = proc.communicate(timeout=300)
    assert proc.returncode == 128 + sig, text
    assert "Traceback" not in text, text
    m = re.search(r"Resume with:\n\s+(python \S+ .*)", text)
    assert m, text
    command = m.group(1).split()
    assert command[1] == "train_driver.py" and "trainer.resume=true" in command
    assert "hydra.run.dir=run" in command  # relative to the folder the command was started in
    step = load_checkpoint(run_dir / "checkpoints" / "last.pt")["step"]
    assert 3 <= step < 10 and max(_losses(run_dir)) == step  # the step in progress was finished and saved
    done = subprocess.run([sys.executable, str(DRIVER), *command[2:]], cwd=tmp_path, env=_env(), capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert _losses(run_dir) == _losses(Path(ref["output_dir"]))  # bit-identical continuation


@pytest.mark.slow
def test_resume_without_a_run_folder_is_a_clear_error(tmp_path):
    old = tmp_path / "outputs" / "2026-01-01" / "10-00-00.000_1" / "checkpoints"
    old.mkdir(parents=True)
    (old / "last.pt").write_bytes(b"")
    out = subprocess.run([sys.executable, str(DRIVER), *RUN, "trainer.max_steps=2", "trainer.resume=true"],
                         cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=300)
    text = out.stdout + out.stderr
    assert out.returncode != 0
    assert "trainer.resume=true needs the folder of the run" in text and f"hydra.run.dir={old.parent}" in text, text


def _check_pair(ck_dir: Path) -> None:
    """Both files load; last.pt's best step has its best.pt (or a later one that the resume redoes)."""
    last = load_checkpoint(ck_dir / "last.pt") if (ck_dir / "last.pt").exists() else None
    best = load_checkpoint(ck_dir / "best.pt") if (ck_dir / "best.pt").exists() else None
    if last is not None and last["best_step"] >= 0:
        assert best is not None, f"last.pt (step {last['step']}) records best step {last['best_step']}, no best.pt"
        assert best["step"] == last["best_step"] or best["step"] > last["step"], (best["step"], last["best_step"])


@pytest.mark.slow
def test_kill_storm_never_loses_a_checkpoint_and_resume_stays_exact(tmp_path, cfg_factory):
    over = RUN + ["trainer.max_steps=16", "trainer.val_every_steps=2", "trainer.ckpt_every_steps=1",
                  "trainer.ckpt_every_minutes=0", "trainer.val_every_minutes=0"]
    ref = train(cfg_factory(over, sub="ref"))
    run_dir = tmp_path / "storm"
    ck_dir = run_dir / "checkpoints"
    cmd = [sys.executable, str(DRIVER), *over, f"hydra.run.dir={run_dir}", "trainer.resume=true"]
    rng = random.Random(0)
    # kills right after a given checkpoint write (2, 3: best.pt then last.pt of a validation; 1: last.pt) ...
    plan = [("writes", 2), ("writes", 3), ("writes", 1), ("writes", 2)]
    t0, kills = time.time(), 0
    while plan or time.time() - t0 < 12:  # the planned kills, then random ones for the rest of 12 s (~25 s in all)
        kind, arg = plan.pop(0) if plan else ("random", rng.uniform(0.0, 0.6))
        env = _env(OMNIDL_TEST_STEP_SLEEP=0.03,
                   **({"OMNIDL_TEST_KILL_AFTER_WRITES": arg} if kind == "writes" else {}))
        log_file = run_dir / "train_log.jsonl"
        before = log_file.stat().st_mtime_ns if log_file.exists() else 0
        proc = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        if kind == "random":  # ... and at random moments once this process trains (often mid-write)
            start = time.time()
            while proc.poll() is None and time.time() - start < 300 and (
                    not log_file.exists() or log_file.stat().st_mtime_ns == before):
                time.sleep(0.02)
            time.sleep(arg)
            proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=300)
        kills += proc.returncode == -signal.SIGKILL
        _check_pair(ck_dir)
        if proc.returncode == 0:  # finished before the kill: start over to keep killing
            break
    assert kills >= 4
    done = subprocess.run(cmd, cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    _check_pair(ck_dir)
    assert _losses(run_dir) == _losses(Path(ref["output_dir"]))
    assert load_checkpoint(ck_dir / "best.pt")["step"] == ref["best_step"]
    assert sorted(p.name for p in ck_dir.iterdir()) == ["best.pt", "last.pt"]  # no orphan temp files
