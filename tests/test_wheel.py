"""The package works installed, outside a source checkout (issue 49 item 2).

Builds the wheel from a copy of the sources (PEP 517 ``build_wheel`` of setuptools, no build isolation: nothing
is downloaded and the checkout gets no ``build/`` folder), installs it with ``pip --no-deps`` into a fresh
virtual environment outside the checkout whose ``site-packages`` also sees the running environment's
(``sys.executable``'s, e.g. CI's ``.ci-venv``) through a ``.pth`` file, so the dependencies are reused
and the editable install of the checkout is not (``.pth`` files of a path added that way are not run). Then,
from a temporary folder outside the checkout, with that environment's ``omnidl`` script:

* ``omnidl -h`` lists every subcommand;
* the installed package is the wheel's (not the checkout), its configs are inside it and the camera preset
  ``kb_f195`` resolves (``omnidl calib show kb_f195``);
* ``omnidl train model=fredsnet`` (the README's main job, smoke size) writes ``outputs/<date>/<time>/``
  under the current folder with its checkpoint;
* ``omnidl predict depth`` runs that checkpoint on an image.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
#: the README's smoke suffix for the main job (tests/test_readme.py SMOKE_TRAIN + PANO_64)
SMOKE = ["trainer=debug", "trainer.max_steps=1", "trainer.val_max_batches=1", "trainer.batch_size=1",
         "++data.train_length=1", "++data.val_length=1", "++data.test_length=1", "trainer.tensorboard=false",
         "trainer.num_threads=1", "trainer.progress=false", "data.width=64", "data.height=32"]


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.update(OMP_NUM_THREADS="1", MPLBACKEND="Agg", PYTHONNOUSERSITE="1")
    return env


def _run(cmd: list[str], cwd: Path, timeout: int = 240) -> subprocess.CompletedProcess:
    r = subprocess.run([str(c) for c in cmd], cwd=cwd, env=_env(), capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, f"{' '.join(map(str, cmd))} (in {cwd}) exited {r.returncode}:\n{r.stdout[-3000:]}\n" \
                              f"{r.stderr[-3000:]}"
    return r


def build_wheel(dest: Path) -> Path:
    """The wheel of a copy of the checkout's sources (``pyproject.toml``, ``README.md``, ``omnidl/``)."""
    src = dest / "src"
    src.mkdir(parents=True)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    shutil.copytree(ROOT / "omnidl", src / "omnidl", symlinks=False,
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.so", "*_best.yaml"))
    out = dest / "dist"
    out.mkdir()
    code = "import sys, setuptools.build_meta as b; print(b.build_wheel(sys.argv[1]))"
    name = _run([sys.executable, "-c", code, out], src).stdout.strip().splitlines()[-1]
    return out / name


def make_venv(dest: Path) -> Path:
    """A fresh venv (no pip) whose ``site-packages`` also sees the running environment's; returns its python."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(dest)], check=True, env=_env())
    py = dest / ("Scripts/python.exe" if os.name == "nt" else "bin/python")
    purelib = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             check=True, capture_output=True, text=True, env=_env()).stdout.strip()
    ours = dict.fromkeys([sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]])
    Path(purelib, "_omnidl_test_deps.pth").write_text("".join(f"{p}\n" for p in ours))
    return py


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """``(python, omnidl script, work folder, timings)`` of the wheel installed in a fresh venv."""
    base = tmp_path_factory.mktemp("wheel")
    assert ROOT not in base.parents, "the temporary folder must be outside the checkout"
    t = {}
    t0 = time.perf_counter()
    wheel = build_wheel(base / "build")
    t["build"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    py = make_venv(base / "venv")
    _run([sys.executable, "-m", "pip", "--python", py, "install", "--no-deps", "--no-index", "-q",
          "--disable-pip-version-check", wheel], base)
    t["install"] = time.perf_counter() - t0
    script = py.parent / ("omnidl.exe" if os.name == "nt" else "omnidl")
    assert script.is_file(), f"pip installed no omnidl console script in {py.parent}"
    work = base / "work"
    work.mkdir()
    return py, script, work, t


def test_the_installed_package_is_the_wheel_with_its_configs_and_presets(installed):
    py, script, work, _ = installed
    code = ("import omnidl, omnidl.engine.config as c; from omnidl.cameras import resolve_camera, CAMERA_CONFIG_DIR; "
            "cam = resolve_camera('kb_f195'); "
            "print(omnidl.__file__, c.config_root(), CAMERA_CONFIG_DIR, type(cam).__name__, cam.width, cam.height)")
    pkg, configs, presets, name, w, h = _run([py, "-c", code], work).stdout.split()
    pkg, configs, presets = Path(pkg), Path(configs), Path(presets)
    assert py.parents[1] in pkg.parents, f"omnidl imported from {pkg}, not from the venv {py.parents[1]}"
    assert ROOT not in pkg.parents and configs.parent == pkg.parent and presets == configs / "camera"
    assert (configs / "train.yaml").is_file() and (presets / "kb_f195.yaml").is_file()
    assert (name, w, h) == ("KannalaBrandt", "1080", "960")
    helptext = _run([script, "-h"], work).stdout
    for cmd in ("train", "evaluate", "predict", "export", "synth", "reproject", "calib", "report"):
        assert f"\n  {cmd} " in helptext, f"omnidl -h does not list {cmd}:\n{helptext}"


def test_calib_show_a_preset_installed(installed):
    _, script, work, _ = installed
    out = _run([script, "calib", "show", "kb_f195", "--out", "f195.png"], work).stdout
    assert "195.00 deg" in out and (work / "f195.png").stat().st_size > 0


def test_train_the_main_job_then_predict_installed(installed):
    import cv2
    import numpy as np

    py, script, work, timings = installed
    t0 = time.perf_counter()
    _run([script, "train", "model=fredsnet", *SMOKE], work)
    timings["train"] = time.perf_counter() - t0
    runs = sorted(work.glob("outputs/*/*/checkpoints/best.pt"))
    assert len(runs) == 1, f"expected one outputs/<date>/<time>/checkpoints/best.pt under {work}: {runs}"
    run_dir = runs[0].parents[1]
    assert (run_dir / "metrics.json").is_file() and (run_dir / ".hydra" / "config.yaml").is_file()
    assert (run_dir / "train.log").is_file()  # Hydra's job name stays "train", as with python train.py
    rng = np.random.default_rng(0)
    cv2.imwrite(str(work / "room.png"), rng.integers(0, 256, (32, 64, 3), dtype=np.uint8))
    t0 = time.perf_counter()
    _run([script, "predict", "depth", "room.png", "--checkpoint", runs[0], "--out", "pred", "--no-ply",
          "--upright", "off"], work)
    timings["predict"] = time.perf_counter() - t0
    depth = np.load(work / "pred" / "room_depth.npy")
    assert depth.shape == (32, 64) and np.isfinite(depth).all()
    print("wheel test timings (s): " + ", ".join(f"{k} {v:.1f}" for k, v in timings.items()))
