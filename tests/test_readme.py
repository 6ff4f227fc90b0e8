"""The README is a contract: every shell command in it runs, in a smoke size, and writes what it promises.

Commands are the lines starting with ``python``, ``pip``, ``pytest``, ``torchrun`` or ``omnidl`` in the README's
unlabelled/``bash`` code fences and 4-space-indented blocks (``\\`` continuations joined, ``# comments`` and
``[optional ...]`` arguments dropped), plus those in ``docs/*.md`` fences preceded by a
``<!-- runnable-commands -->`` line. Each one must match a :data:`RECIPES` entry saying how it runs in smoke
mode: the same command with the smoke suffix appended (train/evaluate: ``SMOKE_TRAIN``, one step at a tiny
size; CLIs: their smallest sizes) and placeholders (``<best.pt>``, ``FRAMES``, ``DIR``, ...) replaced by
files made here, or why it cannot run here (external data or weights).

* ``test_every_command_has_a_recipe`` / ``test_commands_compose`` (fast): a new README command without a
  recipe, a config choice that no longer exists, or a misspelt override fails here in seconds.
* ``test_readme_command`` (``slow``): runs each command as a subprocess in a temporary folder and checks
  exit status 0 and the promised outputs. ``.ci/run`` runs them; locally ``pytest tests/test_readme.py``.
"""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MARKER = "<!-- runnable-commands -->"

#: appended to every ``train.py``/``evaluate.py`` command (documented in the README, "Every command here runs")
SMOKE_TRAIN = ("trainer=debug trainer.max_steps=1 trainer.val_max_batches=1 trainer.batch_size=1 "
               "++data.train_length=1 ++data.val_length=1 ++data.test_length=1 trainer.tensorboard=false "
               "trainer.num_threads=1 trainer.progress=false")
SMOKE_EVAL = "eval.max_images=1 trainer.num_threads=1 trainer.progress=false"
PANO_64 = "data.width=64 data.height=32"


@dataclass(frozen=True)
class Command:
    text: str
    source: str          # file:line

    @property
    def id(self) -> str:
        return f"{self.source} {self.text[:70]}"


@dataclass(frozen=True)
class Recipe:
    """How a README command runs in smoke mode.

    ``pattern`` is searched in the command; ``smoke`` is appended; ``subs`` are ``(regex, replacement)`` pairs
    applied first (``{tmp}`` the test's folder, ``{ckpt:<model>}`` a checkpoint of that model, ``{fisheye}`` the
    fisheye image, calibration and checkpoint of ``tests/apps/test_predict_helpers.readme_fisheye_fixture``, ``{frames}`` a
    folder of panoramas, ``{sweep}`` a multirun folder); ``outputs`` are globs under ``{tmp}`` that must exist;
    ``produces`` names what the command leaves for later commands; ``skip`` says why it cannot run here; ``fresh``
    runs it in a new interpreter even where the zygote could (tests/zygote.py)."""

    pattern: str
    smoke: str = ""
    subs: tuple[tuple[str, str], ...] = ()
    outputs: tuple[str, ...] = ()
    produces: str | None = None
    skip: str | None = None
    timeout: int = 600
    fresh: bool = False


_RUN = "hydra.run.dir={tmp}/run"
_CKPT = r"(outputs/<date>/<time>/checkpoints/best\.pt|<best\.pt>|RUN/checkpoints/best\.pt|outputs/<run>/checkpoints/best\.pt|outputs/\.\.\./best\.pt)"

RECIPES: list[Recipe] = [
    # set-up: .ci/run is exactly `pip install -e ".[dev]" && pytest`; the main job runs below without the pip part
    Recipe(r"^pip install -e \"\.\[dev\]\" && pytest$", skip="the second set-up command is .ci/run itself"),
    Recipe(r"^pip install -e \. && python train\.py model=fredsnet$", subs=((r"^pip install -e \. && ", ""),),
           smoke=f"{SMOKE_TRAIN} {PANO_64} {_RUN}", outputs=("run/checkpoints/best.pt", "run/metrics.json"),
           produces="ckpt:fredsnet", fresh=True),
    # external data or weights this machine does not have
    Recipe(r"data=stanford2d3ds", skip="needs the Stanford2D3DS dataset (data.root)"),
    Recipe(r"data=matterport3d|data=zind|data=pano_annotator", skip="needs a real dataset (data.root)"),
    Recipe(r"model\.pretrained=/path/", skip="needs ImageNet ResNet-50 weights on disk"),
    Recipe(r"convert_fredsnet", skip="needs the official FreDSNet weights file"),
    Recipe(r"loss=fredsnet_loss_weights_best", skip="needs the 20-trial search's result (configs/loss/*_best.yaml)"),
    # benchmarks: one repetition each (their figures need an idle machine)
    Recipe(r"^python benchmarks/fredsnet\.py$",
           smoke="--reps 1 --warmup 1 --backbone resnet18 --width 0.125 --skip-equi --threads 1"),
    Recipe(r"^python benchmarks/layout\.py$", smoke="--reps 1 --threads 1"),
    Recipe(r"^python benchmarks/gyroscope\.py accuracy$", smoke="--reps 1 --n 2 --threads 1 --out {tmp}/gyro",
           outputs=("gyro/*",)),
    Recipe(r"^python benchmarks/gyroscope\.py speed$", smoke="--reps 1 --warmup 1 --threads 1"),
    Recipe(r"^python -m benchmarks\.", skip="a speed benchmark (run by hand on an idle machine)"),
    # training and evaluation
    Recipe(r"^torchrun ", subs=((r"^torchrun --nproc_per_node=2", "torchrun --standalone --nproc_per_node=2"),
                                (r"trainer\.max_steps=\d+", "")),
           smoke=f"{SMOKE_TRAIN} {PANO_64} trainer.batch_size=1 {_RUN}", outputs=("run/checkpoints/last.pt",)),
    Recipe(r"^python train\.py -m ", smoke=f"{SMOKE_TRAIN} {PANO_64} hydra.sweep.dir={{tmp}}/sweep",
           outputs=("sweep/0/metrics.json",), produces="sweep"),
    Recipe(r"\+search=", smoke=f"{SMOKE_TRAIN} {PANO_64} search.trials=1 search.sobol_trials=1 "
                                "search.dir={tmp}/search search.config_dir={tmp}/configs hydra.run.dir={tmp}/run",
           outputs=("search/trials.csv",)),
    Recipe(r"^python evaluate\.py .*postprocess=", subs=((_CKPT, "{ckpt:horizonnet_nc}"),),
           smoke=f"{SMOKE_EVAL} {_RUN}", outputs=("run/metrics.json", "run/postprocess.jsonl")),
    Recipe(r"^python evaluate\.py .*data=folder", subs=((_CKPT, "{ckpt:fredsnet}"), (r"my_panos/", "{frames}")),
           smoke=f"{SMOKE_EVAL} {_RUN}", outputs=("run/images/pano0.png", "run/report.html")),
    Recipe(r"^python evaluate\.py .*rotation_deg", subs=((_CKPT, "{ckpt:fredsnet}"),),
           smoke=f"{SMOKE_EVAL} {_RUN}", outputs=("run/rotation.csv", "run/rotation.png")),
    Recipe(r"^python evaluate\.py ", subs=((_CKPT, "{ckpt:fredsnet}"),),
           smoke=f"{SMOKE_EVAL} {_RUN}", outputs=("run/metrics.json", "run/per_image.csv", "run/report.html")),
    Recipe(r"^python train\.py model=horizonnet_nc$", smoke=f"{SMOKE_TRAIN} {_RUN}",
           outputs=("run/checkpoints/best.pt",), produces="ckpt:horizonnet_nc"),
    Recipe(r"^python train\.py model=horizonnet$", smoke=f"{SMOKE_TRAIN} {_RUN}",
           outputs=("run/checkpoints/best.pt",), produces="ckpt:horizonnet"),
    Recipe(r"^python train\.py model=holinet_small$", smoke=f"{SMOKE_TRAIN} {_RUN}",
           outputs=("run/checkpoints/best.pt",), produces="ckpt:holinet_small"),
    Recipe(r"^python train\.py model=fredsnet$", smoke=f"{SMOKE_TRAIN} {PANO_64} {_RUN}",
           outputs=("run/checkpoints/best.pt", "run/metrics.json"), produces="ckpt:fredsnet", fresh=True),
    Recipe(r"^python train\.py .*model=(fredsnet|holinet)\b", smoke=f"{SMOKE_TRAIN} {PANO_64} {_RUN}",
           outputs=("run/checkpoints/last.pt",)),
    Recipe(r"^python train\.py ", smoke=f"{SMOKE_TRAIN} {_RUN}", outputs=("run/checkpoints/last.pt",)),
    # command-line tools
    Recipe(r"^pip install -e \"\.\[video\]\"", skip="an install step for an optional extra (CI installs .[dev])"),
    Recipe(r"--model depth_anything_v2 --weights", skip="needs Depth-Anything-V2 weights on disk (docs/foundation.md)"),
    Recipe(r"^omnidl predict depth my_fisheye\.jpg --camera calib\.yaml ",
           subs=((r"my_fisheye\.jpg", "{fisheye}/my_fisheye.jpg"), (r"calib\.yaml", "{fisheye}/calib.yaml"),
                 (_CKPT, "{fisheye}/ckpt.pt"), (r"--out pred/", "--out {tmp}/pred/")),
           outputs=("pred/my_fisheye_depth.npy", "pred/my_fisheye_predict.json")),
    Recipe(r"^omnidl predict depth ", subs=((r"my_panos/", "{frames}/"), (_CKPT, "{ckpt:fredsnet}"),
                                            (r"--out pred/", "--out {tmp}/pred/")),
           outputs=("pred/pano0_depth.png", "pred/pano0.ply", "pred/pano0_figure.png")),
    Recipe(r"^omnidl predict layout ", subs=((r"room\.jpg", "{frames}/pano0.png"),
                                             (r"--checkpoint \S+", "--checkpoint {ckpt:horizonnet}"),
                                             (r"--out pred/", "--out {tmp}/pred/")),
           outputs=("pred/pano0_layout.json",)),
    Recipe(r"^omnidl predict upright ", subs=((r"tilted\.mp4", "{frames}/pano0.png"), (r"--out pred/", "--out {tmp}/pred/")),
           outputs=("pred/pano0_upright.json",)),
    Recipe(r"^omnidl predict stabilise ", subs=((r"frames/ ", "{frames}/ "), (r"--out stab/", "--out {tmp}/stab/")),
           outputs=("stab/rotations.csv",)),
    Recipe(r"^python -m omnidl\.apps\.synth ", subs=((r"--n \d+", "--n 1"), (r"datasets/", "{tmp}/")),
           smoke="--width 64 --height 32", outputs=("*/contact_sheet.png",)),
    Recipe(r"^python -m omnidl\.apps\.reproject ", subs=((r"--src pano\.png", "--src {frames}/pano0.png"),
                                                        (r"--out f\.png", "--out {tmp}/f.png")),
           outputs=("f.png",)),
    Recipe(r"^python -m omnidl\.apps\.layout\.acceptance", subs=((r"--n \d+", "--n 1"),), smoke="--width 128"),
    Recipe(r"^python -m omnidl\.apps\.layout\.noise_study", subs=((r"--out DIR", "--out {tmp}/study"),),
           smoke="--rooms 1 --reps 1 --width 128", outputs=("study/noise_study.md",)),
    Recipe(r"^python -m omnidl\.apps\.gyroscope .*--assume-upright",
           subs=((r"FRAMES", "{frames}"), (r"--out OUT", "--out {tmp}/gyro")), outputs=("gyro/rotations.csv",)),
    Recipe(r"^python -m omnidl\.apps\.gyroscope .*--checkpoint",
           skip="needs a trained HoLiNet: a 1-step smoke model finds no horizon (the --assume-upright line runs)"),
    Recipe(r"^python -m omnidl\.apps\.gyroscope ", subs=((r"FRAMES", "{frames}"), (r"--out OUT", "--out {tmp}/gyro"),
                                                       (_CKPT, "{ckpt:holinet_small}")),
           outputs=("gyro/rotations.csv",)),
    Recipe(r"^python -m omnidl\.apps\.fisheye\.protocol ",
           smoke="--out {tmp}/fisheye train.steps=2 finetune.steps=1 panoramas.train.length=2 "
                 "panoramas.test.length=1 views_per_panorama=1 panoramas.train.cache_dir=null "
                 "panoramas.test.cache_dir=null", outputs=("fisheye/tables.md",)),
    Recipe(r"^python -m omnidl\.apps\.report ", subs=((r"multirun/<date>/<time>", "{sweep}"),),
           smoke="--out {tmp}/report", outputs=("report/results.md",)),
]


def _commands_in(text: str, source: str, whole: bool) -> list[Command]:
    """Command lines of the fenced (``whole``: every unlabelled/bash fence and indented block; else only fences
    after :data:`MARKER`) blocks of a markdown text."""
    out: list[Command] = []
    blocks = []
    for m in re.finditer(r"^(<!-- runnable-commands -->\n)?```(\w*)\n(.*?)^```", text, re.S | re.M):
        if m.group(2) in ("", "bash", "sh", "shell", "console") and (whole or m.group(1)):
            blocks.append((m.start(3), m.group(3)))
    if whole:
        fenced = [(m.start(), m.end()) for m in re.finditer(r"^```.*?^```", text, re.S | re.M)]
        for m in re.finditer(r"(?:^ {4,}\S.*\n)+", text, re.M):
            if not any(a <= m.start() < b for a, b in fenced):
                blocks.append((m.start(), m.group(0)))
    for start, body in blocks:
        first_line = text.count("\n", 0, start) + 1
        lines = body.split("\n")
        i = 0
        while i < len(lines):
            line, n0 = lines[i], i
            while line.rstrip().endswith("\\") and i + 1 < len(lines):
                i += 1
                line = line.rstrip()[:-1] + " " + lines[i].strip()
            i += 1
            cmd = re.sub(r"\s+#.*$", "", line.strip())
            cmd = re.sub(r"\s+\[-[^\]]*\]", "", cmd).strip()           # [--optional arguments]
            if re.match(r"(python|pip|pytest|torchrun|omnidl)(\s|$)", cmd):
                out.append(Command(re.sub(r"\s+", " ", cmd), f"{source}:{first_line + n0}"))
    return out


def readme_commands() -> list[Command]:
    """Every command of README.md, then the marked ones of docs/*.md; a command written twice is run once."""
    cmds = _commands_in(README.read_text(encoding="utf-8"), "README.md", whole=True)
    for doc in sorted((ROOT / "docs").glob("*.md")):
        cmds += _commands_in(doc.read_text(encoding="utf-8"), f"docs/{doc.name}", whole=False)
    seen: set[str] = set()
    return [c for c in cmds if not (c.text in seen or seen.add(c.text))]


def recipe_for(cmd: Command) -> Recipe | None:
    return next((r for r in RECIPES if re.search(r.pattern, cmd.text)), None)


COMMANDS = readme_commands()


def test_the_readme_opens_with_the_two_setup_commands():
    first = re.search(r"^```\n(.*?)^```", README.read_text(encoding="utf-8"), re.S | re.M).group(1)
    lines = [re.sub(r"\s+#.*$", "", ln).strip() for ln in first.strip().splitlines()]
    assert lines == ["pip install -e . && python train.py model=fredsnet", 'pip install -e ".[dev]" && pytest']


def test_every_command_has_a_recipe():
    assert len(COMMANDS) >= 30, f"found only {len(COMMANDS)} README commands: is the extraction broken?"
    missing = [c.id for c in COMMANDS if recipe_for(c) is None]
    assert not missing, ("README commands without a smoke recipe in tests/test_readme.py RECIPES "
                         f"(add one, or say why it cannot run here): {missing}")


def _hydra_overrides(cmd: str) -> tuple[str, list[str]] | None:
    """``(config name, overrides)`` of a ``train.py``/``evaluate.py`` command line (None for other commands)."""
    m = re.search(r"(?:^|\s)(train|evaluate)\.py((?:\s+\S+)*)$", cmd)
    if not m:
        return None
    args = [a for a in shlex.split(m.group(2)) if a not in ("-m", "--multirun")]
    return m.group(1), [a.split(",")[0] if re.match(r"\+?\w+=[\w-]+,", a) else a for a in args]


@pytest.mark.parametrize("cmd", [c for c in COMMANDS if _hydra_overrides(c.text)], ids=lambda c: c.id)
def test_commands_compose(cmd, tmp_path):
    """Every train.py/evaluate.py command composes with its smoke suffix (configs exist, keys are spelt right)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from omnidl.engine.config import register_configs

    recipe = recipe_for(cmd)
    if recipe is None:
        pytest.skip("no recipe (test_every_command_has_a_recipe fails)")
    if re.search(r"=\w+_best\b", cmd.text):
        pytest.skip("names a config a search writes (configs/loss/*_best.yaml, git-ignored)")
    # composing needs no data or weights: commands that cannot run here still compose
    text = _substitute(cmd.text, recipe, lambda m: str(tmp_path / m.group(1).replace(":", "_")))
    name, overrides = _hydra_overrides(text)
    overrides = [o for o in overrides if not o.startswith(("hydra.", "search.dir", "--"))]
    register_configs()
    GlobalHydra.instance().clear()
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "configs"), job_name="readme"):
        cfg = compose(config_name=name, overrides=overrides + ["paths.output_dir=" + str(tmp_path)])
    if name == "train" and not cfg.get("search"):
        assert cfg.get("model") is not None, f"{cmd.source}: `{cmd.text}` selects no model (add model=...)"


# --- running the commands ---------------------------------------------------------------------------------------

def _substitute(text: str, recipe: Recipe, fill) -> str:
    """The command with the recipe's substitutions, then its smoke suffix, then ``{placeholder}`` filled by
    ``fill(match)``."""
    for pat, rep in recipe.subs:
        text = re.sub(pat, rep, text)
    text = f"{text} {recipe.smoke}".strip()
    return re.sub(r"\{([\w:]+)\}", fill, text)


def _frames(base: Path) -> Path:
    """Two small upright panoramas (rendered synthetic rooms) as PNG files in ``base/frames``."""
    import cv2
    import numpy as np

    from omnidl.cameras import build
    from omnidl.synth import place_camera, render, sample_room

    d = base / "frames"
    if d.is_dir():
        return d
    part = base / "frames.part"
    part.mkdir(parents=True, exist_ok=True)
    cam = build({"type": "equirect", "width": 128, "height": 64})
    for i in range(2):
        scene = sample_room(seed=i)
        rgb = render(scene, cam, place_camera(scene, cam, seed=i))["image"]
        img = (rgb.clamp(0, 1).permute(1, 2, 0).numpy()[..., ::-1] * 255).round().astype(np.uint8)
        cv2.imwrite(str(part / f"pano{i}.png"), img)
    part.rename(d)
    return d


def _fisheye(base: Path) -> Path:
    """The README's fisheye example in ``base/fisheye``: ``my_fisheye.jpg``, ``calib.yaml``, ``ckpt.pt``."""
    from tests.apps.test_predict_helpers import readme_fisheye_fixture
    d = base / "fisheye"
    if not (d / "ckpt.pt").is_file():
        readme_fisheye_fixture(d)
    return d


def _needs(recipe: Recipe) -> set[str]:
    """What a recipe's placeholders need from other commands (``ckpt:<model>``, ``sweep``)."""
    text = " ".join([recipe.smoke, *(rep for _, rep in recipe.subs)])
    return {k for k in re.findall(r"\{([\w:]+)\}", text) if k not in ("tmp", "frames", "fisheye")}


def _producer(key: str) -> Command:
    cmd = next((c for c in COMMANDS if (r := recipe_for(c)) is not None and r.produces == key), None)
    assert cmd is not None, f"no README command produces {key}"
    return cmd


@dataclass
class Outcome:
    line: str
    returncode: int
    stdout: str
    stderr: str
    seconds: float
    tmp: Path


#: the environment of every command
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg", "PYTHONUNBUFFERED": "1"}


class Runner:
    """Runs the selected commands in a thread pool (``OMNIDL_README_JOBS`` at a time, default the CPU count up
    to 4), the commands that produce checkpoints and sweeps first, each in its own folder under ``base``.

    A ``python SCRIPT``, ``python -m MODULE`` or ``omnidl`` line runs in a child of the test process's zygote
    (tests/zygote.py ``shared()``: a process that has imported torch and omnidl once; ~3 s of CPU saved per
    command), the main job (``fresh``) and every other line (``torchrun``, shell operators) through ``bash -c`` in
    a new process.
    ``OMNIDL_README_ZYGOTE=0`` runs every line through ``bash -c``."""

    def __init__(self, base: Path, jobs: int):
        from tests.zygote import shared
        self.base, self.pool = base, ThreadPoolExecutor(max_workers=max(1, jobs))
        self.zygote = shared() if os.environ.get("OMNIDL_README_ZYGOTE", "1") != "0" else None
        self.futures: dict[str, Future] = {}
        self.lock, self.frames_lock = threading.Lock(), threading.Lock()

    def start(self, cmds: list[Command]) -> None:
        wanted = [c for c in cmds if recipe_for(c) is not None and not recipe_for(c).skip]
        producers = [_producer(k) for c in wanted for k in sorted(_needs(recipe_for(c)))]
        for c in producers + sorted(wanted, key=lambda c: recipe_for(c).produces is None):
            self.submit(c)

    def submit(self, cmd: Command) -> Future:
        """The run of ``cmd``; commands whose smoke lines are the same (``pip install -e . && python train.py
        model=fredsnet`` of the set-up block and the main job's ``python train.py model=fredsnet``) share one run."""
        key = _substitute(cmd.text, recipe_for(cmd), lambda m: m.group(0))
        with self.lock:
            if key not in self.futures:
                self.futures[key] = self.pool.submit(self._run, cmd, self.base / f"cmd{COMMANDS.index(cmd):02d}")
            return self.futures[key]

    def produced(self, key: str) -> str:
        cmd = _producer(key)
        out = self.submit(cmd).result()
        if out.returncode != 0:
            raise RuntimeError(f"{key} comes from `{cmd.text}` ({cmd.source}), which failed: see its own test")
        return str(out.tmp / "sweep") if key == "sweep" else str(out.tmp / "run" / "checkpoints" / "best.pt")

    def _run(self, cmd: Command, tmp: Path) -> Outcome:
        tmp.mkdir(parents=True, exist_ok=True)

        def fill(m: re.Match) -> str:
            key = m.group(1)
            if key == "tmp":
                return str(tmp)
            if key == "frames":
                with self.frames_lock:
                    return str(_frames(self.base))
            if key == "fisheye":
                with self.frames_lock:
                    return str(_fisheye(self.base))
            return self.produced(key)

        from tests.zygote import forkable, read_text
        recipe = recipe_for(cmd)
        line = _substitute(cmd.text, recipe, fill)
        argv = None if recipe.fresh or self.zygote is None else forkable(line)
        t0 = time.time()
        if argv is None:
            res = subprocess.run(["bash", "-c", line], cwd=ROOT, capture_output=True, text=True,
                                 timeout=recipe.timeout, env=ENV)
            return Outcome(line, res.returncode, res.stdout, res.stderr, time.time() - t0, tmp)
        out, err = tmp.parent / f"{tmp.name}.stdout", tmp.parent / f"{tmp.name}.stderr"
        rc = self.zygote.run(argv, str(ROOT), ENV, str(out), str(err), recipe.timeout)
        return Outcome(line, rc, read_text(out), read_text(err), time.time() - t0, tmp)


@pytest.fixture(scope="session")
def readme_runner(request, tmp_path_factory):
    jobs = int(os.environ.get("OMNIDL_README_JOBS", min(4, os.cpu_count() or 1)))
    runner = Runner(tmp_path_factory.mktemp("readme"), jobs)
    runner.start([item.callspec.params["cmd"] for item in request.session.items
                  if item.originalname == "test_readme_command" and hasattr(item, "callspec")])
    yield runner
    runner.pool.shutdown(wait=False, cancel_futures=True)


@pytest.mark.slow
@pytest.mark.parametrize("cmd", COMMANDS, ids=lambda c: c.id)
def test_readme_command(cmd, readme_runner):
    recipe = recipe_for(cmd)
    assert recipe is not None, f"{cmd.id}: no recipe (see test_every_command_has_a_recipe)"
    if recipe.skip:
        pytest.skip(recipe.skip)
    out = readme_runner.submit(cmd).result()
    assert out.returncode == 0, (f"{cmd.source}: `{cmd.text}` failed in smoke mode (exit {out.returncode}, "
                                 f"{out.seconds:.0f} s)\nran: {out.line}\n{out.stdout[-3000:]}\n{out.stderr[-5000:]}")
    missing = [g for g in recipe.outputs if not any(out.tmp.glob(g))]
    assert not missing, f"{cmd.source}: `{cmd.text}` did not write {missing} (ran: {out.line})\n{out.stderr[-3000:]}"


if __name__ == "__main__":  # list the commands and their recipes
    for c in COMMANDS:
        r = recipe_for(c)
        print(f"{c.source:>16s}  {'SKIP ' + r.skip if r and r.skip else (r.pattern if r else 'NO RECIPE')}\n"
              f"{'':>16s}  {c.text}")
    sys.exit(0)
