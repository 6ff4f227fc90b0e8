"""Command lines and config entry points given bad input (reliability findings §1b, §3, §4–6).

Every CLI runs in-process through its ``main(argv)``. A CLI's ERROR verdict is a non-zero exit with a message
(no traceback): :class:`CLIError` carries what it printed on stderr or its ``SystemExit`` message. A SKIP is a
run that finishes and flags what it left out: :func:`run_cli` turns the warnings it logged or printed on stderr
into Python warnings, which ``expect`` matches. Library entry points (the search spec, Hydra composition,
checkpoint readers) raise their own exceptions.
"""
from __future__ import annotations

import contextlib
import io
import json
import logging
import math
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from tests.robustness.verdicts import ERROR, OK, SKIP, expect, row

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


class CLIError(Exception):
    """A command line stopped with a non-zero exit status; the message is what it said."""


class _Collect(logging.Handler):
    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record):
        self.messages.append(record.getMessage())


def run_cli(main, argv: list[str]) -> str:
    """``main(argv)`` in-process; returns stdout. Non-zero exit -> :class:`CLIError`; logged warnings and
    ``warning``/``skipping`` lines on stderr -> Python warnings (a flagged skip)."""
    out, err, handler = io.StringIO(), io.StringIO(), _Collect()
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                rc = main([str(a) for a in argv])
            except SystemExit as exc:
                rc = exc.code
                if isinstance(rc, str):
                    raise CLIError(rc) from None
    finally:
        root.removeHandler(handler)
    if rc not in (0, None):
        raise CLIError(f"exit status {rc}: {err.getvalue()}")
    flagged = handler.messages + [ln for ln in err.getvalue().splitlines()
                                  if "warning" in ln.lower() or "skipping" in ln.lower()]
    for m in flagged:
        warnings.warn(m)
    return out.getvalue()


# ---------------------------------------------------------------------------------------------------------------
# §1b  python -m omnidl.apps.synth
# ---------------------------------------------------------------------------------------------------------------
def _synth(out, *extra, n=1, size=(32, 16), seed=0, camera="equirect", fmt="horizonnet"):
    size_args = ["--width", size[0], "--height", size[1]] if size else []
    return ["--camera", camera, "--n", n, "--out", out, *size_args, "--seed", seed, "--format", fmt,
            "--contact-sheet", 0, *extra]


def _first_run(out):
    from omnidl.apps.synth import main
    run_cli(main, _synth(out))


def _no_manifest(out):
    _first_run(out)
    (out / "synth.json").unlink()


def _bad_manifest(out):
    _first_run(out)
    (out / "synth.json").write_text("{")


def _a_file(out):
    out.write_text("not a folder")


def _foreign_sheet(out):
    out.mkdir(parents=True)
    (out / "contact_sheet.png").write_bytes(b"a user's picture")


def _locked(out):
    import json as _json
    import os as _os

    from omnidl.utils.io import this_host
    out.mkdir(parents=True)
    (out / ".omnidl.lock").write_text(_json.dumps({"pid": _os.getppid(), "host": this_host(), "what": "synth writer"}))


SYNTH_ROWS = [
    row("1b1-rerun-other-size-and-seed", _first_run, lambda o: _synth(o, n=2, size=(64, 32), seed=5),
        verdict=ERROR, match=r"other settings \(width: 32 there, 64 now.*seed: 0 there, 5 now"),
    row("1b1-rerun-other-seed", _first_run, lambda o: _synth(o, n=2, seed=3), verdict=ERROR,
        match=r"seed: 0 there, 3 now.*another --out.*--overwrite"),
    row("1b1-rerun-other-camera", _first_run, lambda o: _synth(o, camera="equirect_256"), verdict=ERROR,
        match=r"camera: 'equirect' there, 'equirect_256' now"),
    row("1b1-samples-without-synth-json", _no_manifest, lambda o: _synth(o, n=2), verdict=ERROR,
        match=r"already holds 2 sample files .*no synth\.json"),
    row("1b1-corrupt-synth-json", _bad_manifest, lambda o: _synth(o), verdict=ERROR,
        match=r"synth\.json cannot be read"),
    row("1b1-overwrite-replaces", _first_run, lambda o: _synth(o, "--overwrite", size=(64, 32), seed=5), verdict=OK),
    row("1b2-rerun-same-settings-extends", _first_run, lambda o: _synth(o, n=2), verdict=OK),
    row("1b3-area-without-prefix", None, lambda o: _synth(o, "--area", "1", fmt="stanford"), verdict=ERROR,
        match=r"--area '1'.*area_<id>"),
    row("1b4-n-0", None, lambda o: _synth(o, n=0), verdict=OK),
    row("1b5-width-0-height-0", None, lambda o: _synth(o, size=(0, 0)), verdict=ERROR,
        match=r"--width must be an image size >= 2 pixels, got 0"),
    row("1b6-width-negative", None, lambda o: _synth(o, size=(-8, 4)), verdict=ERROR,
        match=r"--width must be an image size >= 2 pixels, got -8"),
    row("1b7-width-7-height-3", None, lambda o: _synth(o, size=(7, 3)), verdict=OK),
    row("1b8-out-is-a-file", _a_file, lambda o: _synth(o), verdict=ERROR, match=r"--out .* is an existing file"),
    row("1b9-unknown-camera", None, lambda o: _synth(o, camera="foocam"), verdict=ERROR,
        match=r"--camera 'foocam': unknown camera 'foocam'"),
    row("1b9-missing-camera-yaml", None, lambda o: _synth(o, camera="nowhere/cam.yaml"), verdict=ERROR,
        match=r"camera file 'nowhere/cam\.yaml' does not exist"),
    row("1b10-rc-negative", None, lambda o: _synth(o, "--rc", -1, camera="noncentral_pano", fmt="noncentral"),
        verdict=ERROR, match=r"rc must be >= 0"),
    row("1b11-rc-0", None, lambda o: _synth(o, "--rc", 0, camera="noncentral_pano", fmt="noncentral"), verdict=OK),
    row("width-without-height", None, lambda o: _synth(o, "--width", 32, size=None), verdict=ERROR,
        match=r"both --width and --height"),
    row("manhattan-ratio-2", None, lambda o: _synth(o, "--manhattan-ratio", 2), verdict=ERROR,
        match=r"--manhattan-ratio is a probability in \[0, 1\], got 2"),
    row("max-tilt-120", None, lambda o: _synth(o, "--max-tilt", 120), verdict=ERROR,
        match=r"--max-tilt must be in \[0, 90\] degrees, got 120"),
    row("threads-0", None, lambda o: _synth(o, "--threads", 0), verdict=ERROR, match=r"--threads must be >= 1"),
    row("start-negative", None, lambda o: _synth(o, "--start", -2), verdict=ERROR, match=r"--start must be >= 0"),
    row("n-negative", None, lambda o: _synth(o, n=-1), verdict=ERROR, match=r"--n must be >= 0, got -1"),
    row("n-not-a-number", None, lambda o: _synth(o, n="abc"), verdict=ERROR, match=r"--n: invalid int value: 'abc'"),
    row("unknown-format", None, lambda o: _synth(o, fmt="bogus"), verdict=ERROR,
        match=r"--format: invalid choice: 'bogus'"),
    row("random-rotation-for-upright-format", None, lambda o: _synth(o, "--rotation", "random"), verdict=ERROR,
        match=r"--format horizonnet needs --rotation upright"),
    row("foreign-contact-sheet", _foreign_sheet, lambda o: _synth(o).__add__(["--contact-sheet", 1]), verdict=ERROR,
        match=r"contact_sheet\.png already exists.*--overwrite"),
    row("folder-locked-by-another-writer", _locked, lambda o: _synth(o), verdict=ERROR,
        match=r"is in use by another synth writer: pid \d+ on host"),
]


@pytest.mark.parametrize("setup, argv, verdict, match", SYNTH_ROWS)
def test_synth_cli(tmp_path, setup, argv, verdict, match):
    from omnidl.apps.synth import main
    out = tmp_path / "ds"
    if setup is not None:
        setup(out)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) if verdict == ERROR else None
    expect(lambda: run_cli(main, argv(out)), verdict, match, error=CLIError)
    if verdict == ERROR:   # a refused run changes nothing on disk
        assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before
        return
    imgs = sorted((out / "img").glob("*.png")) if (out / "img").exists() else []
    shapes = {cv2.imread(str(p)).shape[:2] for p in imgs}
    assert len(shapes) <= 1                    # never a mixed dataset
    if "--n" in argv(out) and argv(out)[argv(out).index("--n") + 1] == 0:
        assert not imgs
    elif "--rc" not in argv(out):
        assert imgs and json.loads((out / "synth.json").read_text())["settings"]["format"] == "horizonnet"


# ---------------------------------------------------------------------------------------------------------------
# §3 35–40  python -m omnidl.apps.gyroscope
# ---------------------------------------------------------------------------------------------------------------
def _pano(yaw_deg=0.0, h=32):
    from omnidl.geometry.rotations import euler_to_matrix
    from omnidl.postprocess.gyroscope.scene import procedural_panorama
    R = euler_to_matrix(torch.tensor(0.0), torch.tensor(0.0), torch.tensor(math.radians(yaw_deg))).double()
    return procedural_panorama(R[None], h, 2 * h, seed=7)[0]


def _png(path, img):
    arr = (img.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)[..., ::-1]
    cv2.imwrite(str(path), np.ascontiguousarray(arr))


def _frames(d, extra=None):
    d.mkdir(parents=True, exist_ok=True)
    _png(d / "e_000000.png", _pano(0.0))
    _png(d / "e_000002.png", _pano(30.0))
    if extra:
        extra(d)
    return d


def _ckpt(tmp, kind):
    from omnidl.engine.checkpoint import save_checkpoint
    p = tmp / f"{kind}.pt"
    if kind == "fredsnet":
        save_checkpoint(p, {"model": {"w": torch.zeros(1)}, "config": {"model": {"name": "fredsnet", "width": 0.0625}}})
    elif kind == "noconfig":
        save_checkpoint(p, {"model": {"w": torch.zeros(1)}})
    elif kind == "text":
        p.write_text("not a checkpoint")
    return p


def _black(d):
    _png(d / "e_000001.png", torch.zeros(3, 32, 64))


def _truncated(d):
    data = (d / "e_000002.png").read_bytes()
    (d / "e_000001.png").write_bytes(data[: len(data) // 3])


def _zero_byte(d):
    (d / "e_000001.png").write_bytes(b"")


def _wrong_size(d):
    _png(d / "e_000001.png", torch.rand(3, 16, 32))


def _gray(d):
    img = (_pano(30.0).mean(0).numpy() * 255 + 0.5).astype(np.uint8)
    cv2.imwrite(str(d / "e_000003.png"), img)


def _black_reference(d):
    _png(d / "e_000000.png", torch.zeros(3, 32, 64))


def _not_2to1(d):
    for p in d.glob("*.png"):
        p.unlink()
    cv2.imwrite(str(d / "e_000000.png"), (np.random.default_rng(0).random((32, 63, 3)) * 255).astype(np.uint8))


FAST = ["--height", 32, "--pvg-level", 3, "--batch-size", 2]
GYRO_ROWS = [
    row("3-35-fredsnet-checkpoint", None, lambda t: ["--checkpoint", _ckpt(t, "fredsnet")], verdict=ERROR,
        match=r"fredsnet\.pt holds a 'fredsnet' model .*HoLiNet.*--assume-upright"),
    row("checkpoint-without-config", None, lambda t: ["--checkpoint", _ckpt(t, "noconfig")], verdict=ERROR,
        match=r"noconfig\.pt: no 'config' with a 'model' entry"),
    row("checkpoint-missing", None, lambda t: ["--checkpoint", t / "none.pt"], verdict=ERROR,
        match=r"checkpoint .*none\.pt does not exist"),
    row("checkpoint-text-file", None, lambda t: ["--checkpoint", _ckpt(t, "text")], verdict=ERROR,
        match=r"could not read checkpoint .*text\.pt"),
    row("3-36-black-frame", _black, lambda t: ["--assume-upright", *FAST], verdict=SKIP,
        match=r"frame e_000001\.png: no estimate \(black/flat frame"),
    row("3-37-truncated-frame", _truncated, lambda t: ["--assume-upright", *FAST], verdict=SKIP,
        match=r"frame e_000001\.png: no estimate"),
    row("3-37-zero-byte-frame", _zero_byte, lambda t: ["--assume-upright", *FAST], verdict=SKIP,
        match=r"frame e_000001\.png: no estimate"),
    row("3-37-wrong-size-frame", _wrong_size, lambda t: ["--assume-upright", *FAST], verdict=SKIP,
        match=r"frame e_000001\.png: no estimate \(frame shape .* differs from the reference"),
    row("3-38-grayscale-frame", _gray, lambda t: ["--assume-upright", *FAST], verdict=OK),
    row("3-39-black-reference", _black_reference, lambda t: ["--assume-upright", *FAST], verdict=ERROR,
        match=r"reference image is black/flat; choose another reference frame"),
    row("3-40-not-2to1", _not_2to1, lambda t: ["--assume-upright", *FAST], verdict=ERROR,
        match=r"reference frame .*e_000000\.png: expected an RGB equirectangular panorama \(3, H, 2H\), got "
              r"shape \(3, 32, 63\)"),
    row("neither-checkpoint-nor-upright", None, lambda t: [], verdict=ERROR,
        match=r"give --checkpoint .* or --assume-upright"),
    row("both-checkpoint-and-upright", None, lambda t: ["--assume-upright", "--checkpoint", _ckpt(t, "fredsnet")],
        verdict=ERROR, match=r"either --checkpoint or --assume-upright, not both"),
    row("reference-out-of-range", None, lambda t: ["--assume-upright", "--reference", 9], verdict=ERROR,
        match=r"reference '9' is neither an index < 2"),
    row("height-0", None, lambda t: ["--assume-upright", "--height", 0], verdict=ERROR,
        match=r"--height must be >= 8, got 0"),
    row("batch-size-0", None, lambda t: ["--assume-upright", "--batch-size", 0], verdict=ERROR,
        match=r"--batch-size must be >= 1, got 0"),
    row("lambda-g-nan", None, lambda t: ["--assume-upright", "--lambda-g", "nan"], verdict=ERROR,
        match=r"--lambda-g must be a finite number >= 0, got nan"),
    row("unknown-coherence", None, lambda t: ["--assume-upright", "--coherence", "x"], verdict=ERROR,
        match=r"--coherence: invalid choice: 'x'"),
]


@pytest.mark.parametrize("extra, argv, verdict, match", GYRO_ROWS)
def test_gyroscope_cli(tmp_path, single_thread, extra, argv, verdict, match):
    from omnidl.apps.gyroscope import main
    frames = _frames(tmp_path / "frames", extra)
    out = tmp_path / "out"
    expect(lambda: run_cli(main, [frames, "--out", out, *argv(tmp_path)]), verdict, match, error=CLIError)
    if verdict != ERROR:
        res = {r["name"]: r for r in json.loads((out / "rotations.json").read_text())["frames"]}
        assert res["e_000002.png"]["status"] == "ok" and abs(res["e_000002.png"]["yaw"] - 30) < 2
        if verdict == SKIP:
            assert res["e_000001.png"]["status"] == "no_estimate" and res["e_000001.png"]["reason"]
        else:   # grayscale: the right yaw
            assert res["e_000003.png"]["status"] == "ok" and abs(res["e_000003.png"]["yaw"] - 30) < 2
    else:
        assert not (out / "rotations.json").exists()


def test_gyroscope_missing_and_empty_folders(tmp_path):
    """§3: the frames folder itself (exit 2 with the path)."""
    from omnidl.apps.gyroscope import main
    expect(lambda: run_cli(main, [tmp_path / "none", "--out", tmp_path / "o", "--assume-upright"]), ERROR,
           r"frames folder .*none does not exist", error=CLIError)
    (tmp_path / "empty").mkdir()
    expect(lambda: run_cli(main, [tmp_path / "empty", "--out", tmp_path / "o", "--assume-upright"]), ERROR,
           r"frames folder .*empty holds no images", error=CLIError)


# ---------------------------------------------------------------------------------------------------------------
# §3 48–50  python -m omnidl.apps.report
# ---------------------------------------------------------------------------------------------------------------
def _job(root, i, metrics, code="F-Std-CE-X", raw=None):
    d = root / str(i)
    (d / ".hydra").mkdir(parents=True)
    (d / ".hydra" / "config.yaml").write_text(f"name: {code}\n")
    (d / "metrics.json").write_text(raw if raw is not None else json.dumps(metrics))


def _good(root):
    _job(root, 0, {"final": {"val/mre": 0.2, "val/delta1": 0.6, "val/miou": 0.4}})


REPORT_ROWS = [
    row("3-48-empty-folder", lambda r: r.mkdir(), verdict=ERROR, match=r"no metrics\.json found below"),
    row("3-48-missing-folder", lambda r: None, verdict=ERROR, match=r"no such folder .*sweep"),
    row("3-49-truncated-metrics-json", lambda r: (_good(r), _job(r, 1, None, raw='{"final": {"val/mre": 0.')),
        verdict=SKIP, match=r"skipping .*1/metrics\.json: "),
    row("metrics-json-a-list", lambda r: (_good(r), _job(r, 1, None, raw="[1, 2]")), verdict=SKIP,
        match=r"skipping .*1/metrics\.json: expected a JSON object"),
    row("3-50-nan-and-string-values", lambda r: _job(r, 0, {"final": {"val/mre": float("nan"), "val/delta1": "abc",
                                                                      "val/miou": 0.4}}), verdict=OK),
    row("percent-miou-is-flagged", lambda r: _job(r, 0, {"final": {"val/mre": 0.2, "val/miou": 42.0}}),
        verdict=SKIP, match=r"val/miou = 42\.0 is outside \[0, 1\]; omnidl writes fractions"),
    row("rotation-with-bad-angles", lambda r: _job(r, 0, {"final": {"val/mre": 0.2},
                                                          "rotation": {"0": {"mre": 0.1}, "x": {"mre": 0.2},
                                                                       "10": 5, "20": {"mre": 0.3}}}), verdict=OK),
]


@pytest.mark.parametrize("make, verdict, match", REPORT_ROWS)
def test_report_cli(tmp_path, make, verdict, match):
    from omnidl.apps.report import main
    root = tmp_path / "sweep"
    make(root)
    out = expect(lambda: run_cli(main, [root]), verdict, match, error=CLIError)
    if verdict != ERROR:
        table = [ln for ln in out.splitlines() if ln.startswith("| F-Std-CE-X")]
        assert len(table) == 1
        assert (root / "results.csv").exists()


def test_report_nan_and_strings_show_as_dash(tmp_path):
    """§3 50: the values themselves."""
    from omnidl.apps.report import main
    _job(tmp_path, 0, {"final": {"val/mre": float("nan"), "val/delta1": "abc", "val/miou": 0.4}})
    out = run_cli(main, [tmp_path])
    assert "| F-Std-CE-X | - | 40.00 |" in out and "mIoU (%)" in out


# ---------------------------------------------------------------------------------------------------------------
# §3 51–52  python -m omnidl.apps.fisheye.protocol (config errors: before any work)
# ---------------------------------------------------------------------------------------------------------------
def _yaml(tmp, text):
    p = tmp / "proto.yaml"
    p.write_text(text)
    return p


FISHEYE_ROWS = [
    row("3-51-missing-config", lambda t: ["--config", t / "nope.yaml"], verdict=ERROR,
        match=r"protocol config .*nope\.yaml' does not exist"),
    row("3-52-no-image-section", lambda t: ["--config", _yaml(t, "panoramas: {}\n")], verdict=ERROR,
        match=r"proto\.yaml' has no 'image' section"),
    row("misspelt-override-key", lambda t: ["train.stpes=5"], verdict=ERROR,
        match=r"bad override .*train\.stpes=5.*small_cpu\.yaml.*Key 'stpes' is not in struct"),
    row("override-without-value", lambda t: ["train.steps"], verdict=ERROR, match=r"bad override .*train\.steps"),
    row("config-not-yaml", lambda t: ["--config", _yaml(t, "image: [unclosed\n")], verdict=ERROR,
        match=r"protocol config .*proto\.yaml.* is not valid YAML"),
]


@pytest.mark.parametrize("argv, verdict, match", FISHEYE_ROWS)
def test_fisheye_protocol_cli(tmp_path, argv, verdict, match):
    from omnidl.apps.fisheye.protocol import main
    expect(lambda: run_cli(main, [*argv(tmp_path), "--out", tmp_path / "out"]), verdict, match, error=CLIError)
    assert not (tmp_path / "out").exists()


def test_fisheye_added_key_and_out_moves_the_cache(tmp_path):
    from omnidl.apps.fisheye.protocol import load_config
    cfg = load_config(None, ["train.steps=3", "+extra.note=1"])
    assert cfg.train.steps == 3 and cfg.extra.note == 1
    cfg.out_dir = str(tmp_path)
    assert cfg.panoramas.train.cache_dir == f"{tmp_path}/pano_cache"


# ---------------------------------------------------------------------------------------------------------------
# layout acceptance and the FreDSNet converter: argument checks
# ---------------------------------------------------------------------------------------------------------------
ACCEPTANCE_ROWS = [
    row("n-0", ["--n", 0], verdict=ERROR, match=r"--n must be >= 1, got 0"),
    row("width-0", ["--width", 0], verdict=ERROR, match=r"--width must be >= 16, got 0"),
    row("rc-negative", ["--rc", -1], verdict=ERROR, match=r"--rc is the rig radius in metres, >= 0; got -1"),
    row("rc-nan", ["--rc", "nan"], verdict=ERROR, match=r"--rc is the rig radius .* got nan"),
    row("unknown-protocol", ["--protocol", "thesys"], verdict=ERROR, match=r"--protocol: invalid choice: 'thesys'"),
]


@pytest.mark.parametrize("argv, verdict, match", ACCEPTANCE_ROWS)
def test_layout_acceptance_cli(argv, verdict, match):
    from omnidl.apps.layout.acceptance import main
    expect(lambda: run_cli(main, argv), verdict, match, error=CLIError)


def _official(tmp, kind):
    p = tmp / "official.pth"
    if kind == "text":
        p.write_text("hello")
    elif kind == "list":
        torch.save([1, 2], p)
    elif kind == "omnidl":
        torch.save({"model": {"encoder.0.weight": torch.zeros(2)}}, p)
    elif kind == "empty":
        torch.save({"state_dict": {}}, p)
    return p


CONVERT_ROWS = [
    row("missing-file", lambda t: [t / "none.pth", t / "o.pth"], verdict=ERROR,
        match=r"official FreDSNet checkpoint '.*none\.pth' not found"),
    row("text-file", lambda t: [_official(t, "text"), t / "o.pth"], verdict=ERROR,
        match=r"official\.pth' could not be read with torch\.load\(weights_only=True\)"),
    row("pickled-list", lambda t: [_official(t, "list"), t / "o.pth"], verdict=ERROR,
        match=r"official\.pth': expected a FreDSNet checkpoint dict with a 'state_dict', got list"),
    row("omnidl-checkpoint-not-official", lambda t: [_official(t, "omnidl"), t / "o.pth"], verdict=ERROR,
        match=r"official\.pth' does not look like the official FreDSNet checkpoint: unexpected key 'model"),
    row("empty-state-dict", lambda t: [_official(t, "empty"), t / "o.pth"], verdict=ERROR,
        match=r"official\.pth': the state dict is empty"),
    row("output-is-the-input", lambda t: [_official(t, "empty"), t / "official.pth"], verdict=ERROR,
        match=r"the output .*official\.pth is the official checkpoint itself"),
    row("output-is-a-folder", lambda t: [_official(t, "empty"), t], verdict=ERROR, match=r"is a folder; give a file"),
    row("output-is-a-hard-link-of-the-input", lambda t: [_official(t, "empty"), _hardlink(t)], verdict=ERROR,
        match=r"is the official checkpoint itself"),
    row("output-exists", lambda t: [_official(t, "empty"), _existing(t)], verdict=ERROR,
        match=r"previous\.pth already exists.*--overwrite"),
]


def _hardlink(t):
    import os as _os
    _os.link(t / "official.pth", t / "link.pth")
    return t / "link.pth"


def _existing(t):
    (t / "previous.pth").write_bytes(b"converted before")
    return t / "previous.pth"


@pytest.mark.parametrize("argv, verdict, match", CONVERT_ROWS)
def test_convert_fredsnet_cli(tmp_path, argv, verdict, match):
    from omnidl.apps.convert_fredsnet import main
    expect(lambda: run_cli(main, argv(tmp_path)), verdict, match, error=CLIError)
    assert not (tmp_path / "o.pth").exists()


# ---------------------------------------------------------------------------------------------------------------
# §3 1–7 and config groups: Hydra composition of train.py's config (fails before any work)
# ---------------------------------------------------------------------------------------------------------------
def _compose(overrides):
    from hydra import compose, initialize_config_dir
    from omnidl.engine.config import register_configs
    register_configs()
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose(config_name="train", overrides=list(overrides))


CONFIG_ROWS = [
    row("3-1-misspelt-trainer-key", ["model=fredsnet", "trainer.max_stpes=3"], verdict=ERROR, match=r"max_stpes"),
    row("3-2-steps-not-a-number", ["model=fredsnet", "trainer.max_steps=abc"], verdict=ERROR,
        match=r"max_steps.*abc|abc.*max_steps"),
    row("3-3-unknown-model", ["model=foonet"], verdict=ERROR, match=r"Could not find 'model/foonet'"),
    row("3-4-misspelt-model-key", ["model=fredsnet", "model.widht=0.1"], verdict=ERROR, match=r"widht"),
    row("3-5-misspelt-data-key", ["model=fredsnet", "data.widht=64"], verdict=ERROR, match=r"widht"),
    row("3-6-explicit-new-key", ["model=fredsnet", "+data.widht=64"], verdict=OK),
    row("3-7-misspelt-loss-key", ["model=fredsnet", "loss.alpha_semantc=3"], verdict=ERROR, match=r"alpha_semantc"),
    row("unknown-experiment", ["experiment=F-Std-CE-Z"], verdict=ERROR,
        match=r"Could not find 'experiment/F-Std-CE-Z'"),
    row("unknown-search", ["+search=fredsnet_tny"], verdict=ERROR, match=r"Could not find 'search/fredsnet_tny'"),
    row("unknown-data", ["model=fredsnet", "data=stanford2d3dz"], verdict=ERROR,
        match=r"Could not find 'data/stanford2d3dz'"),
    row("ablation-B-without-search-result", ["experiment=F-Std-CE-B"], verdict=OK),
    row("fisheye-experiment", ["experiment=fisheye_f195_calib"], verdict=OK),
]


@pytest.mark.parametrize("overrides, verdict, match", CONFIG_ROWS)
def test_train_config_composition(overrides, verdict, match):
    cfg = expect(lambda: _compose(overrides), verdict, match)
    if verdict == OK:
        assert cfg.model is not None


# ---------------------------------------------------------------------------------------------------------------
# §4–6 7–11 and search config values: python train.py +search=...
# ---------------------------------------------------------------------------------------------------------------
def _search_cfg(tmp, **search):
    from omegaconf import OmegaConf
    return OmegaConf.create({
        "loss": {"alpha_a": 1.0}, "paths": {"output_dir": "unused"},
        "search": {"name": "toy", "trials": 1, "sobol_trials": 1, "dir": str(tmp / "s"),
                   "config_dir": str(tmp / "configs"), "objective": {"metrics": {"err": 1.0}, "minimize": True},
                   "parameters": {"loss.alpha_a": {"bounds": [0.01, 100], "log": True}}, **search}})


def _toy_train(cfg):
    return {"err": math.log10(cfg.loss.alpha_a) ** 2}


@pytest.fixture(scope="module")
def saved_search(tmp_path_factory):
    """One finished 1-trial search (its state files), made once for the resume rows."""
    from omnidl.search import run_search_from_config
    d = tmp_path_factory.mktemp("search")
    run_search_from_config(_search_cfg(d), train_fn=_toy_train)
    return {p.name: p.read_bytes() for p in (d / "s").iterdir() if p.is_file()}


def _cut(name):
    def f(files):
        files[name] = files[name][: len(files[name]) // 2]
    return f


def _put(name, data):
    def f(files):
        files[name] = data
    return f


SEARCH_STATE_ROWS = [
    row("4-7-experiment-json-cut-in-half", _cut("experiment.json"), {}, verdict=ERROR,
        match=r"search state file .*experiment\.json \(the Ax experiment\) is not valid JSON.*search\.restart=true"),
    row("4-8-experiment-json-hello", _put("experiment.json", b"hello"), {}, verdict=ERROR,
        match=r"experiment\.json \(the Ax experiment\) is not valid JSON"),
    row("4-9-experiment-json-empty", _put("experiment.json", b""), {}, verdict=ERROR,
        match=r"experiment\.json \(the Ax experiment\) is not valid JSON"),
    row("experiment-json-not-ax", _put("experiment.json", b'{"a": 1}'), {}, verdict=ERROR,
        match=r"experiment\.json is not a saved Ax experiment"),
    row("4-10-trials-json-cut-in-half", _cut("experiment_trials.json"), {}, verdict=ERROR,
        match=r"experiment_trials\.json \(the per-trial records\) is not valid JSON"),
    row("4-11-flipped-direction", None, {"objective": {"metrics": {"err": 1.0}, "minimize": False}}, verdict=ERROR,
        match=r"search\.objective\.minimize: saved True, now False.*search\.restart=true"),
    row("changed-objective-weight", None, {"objective": {"metrics": {"err": 0.01}, "minimize": True}}, verdict=ERROR,
        match=r"search\.objective\.metrics\.err: saved 1\.0, now 0\.01"),
    row("changed-bounds", None, {"parameters": {"loss.alpha_a": {"bounds": [0.1, 10], "log": True}}}, verdict=ERROR,
        match=r"search\.parameters\.loss\.alpha_a\.bounds: saved \[0\.01, 100\.0\], now \[0\.1, 10\.0\]"),
    row("changed-trial-budget", None, {"overrides": ["trainer.max_steps=8"]}, verdict=ERROR,
        match=r"search\.overrides: saved \[\], now \['trainer\.max_steps=8'\]"),
    row("flipped-direction-with-override", None, {"objective": {"metrics": {"err": 1.0}, "minimize": False},
                                                  "resume_override": True}, verdict=OK),
    row("more-trials-resume", None, {"trials": 2}, verdict=OK),
]


@pytest.mark.parametrize("damage, change, verdict, match", SEARCH_STATE_ROWS)
def test_search_resume(tmp_path, saved_search, damage, change, verdict, match):
    from omnidl.search import SearchStateError, run_search_from_config
    files = dict(saved_search)
    if damage:
        damage(files)
    (tmp_path / "s").mkdir()
    for name, data in files.items():
        (tmp_path / "s" / name).write_bytes(data)
    calls = []

    def train(cfg):
        calls.append(cfg)
        return _toy_train(cfg)
    res = expect(lambda: run_search_from_config(_search_cfg(tmp_path, **change), train_fn=train), verdict, match,
                 error=SearchStateError)
    if verdict == ERROR:
        assert not calls                                    # refused before any trial
    else:
        assert len(res.completed) >= 1


SPEC_ROWS = [
    row("trials-0", {"trials": 0}, verdict=ERROR, match=r"search\.trials: must be >= 1, got 0"),
    row("trials-abc", {"trials": "abc"}, verdict=ERROR, match=r"search\.trials: expected an integer, got 'abc'"),
    row("sobol-negative", {"sobol_trials": -1}, verdict=ERROR, match=r"search\.sobol_trials: must be >= 0"),
    row("max-failures-0", {"max_failures": 0}, verdict=ERROR, match=r"search\.max_failures: must be >= 1"),
    row("bounds-reversed", {"parameters": {"loss.alpha_a": {"bounds": [10, 1]}}}, verdict=ERROR,
        match=r"search\.parameters\.loss\.alpha_a\.bounds: empty or invalid range \[10\.0, 1\.0\]"),
    row("bounds-one-number", {"parameters": {"loss.alpha_a": {"bounds": [1]}}}, verdict=ERROR,
        match=r"alpha_a\.bounds: expected \[low, high\]"),
    row("log-from-zero", {"parameters": {"loss.alpha_a": {"bounds": [0, 1], "log": True}}}, verdict=ERROR,
        match=r"log scale needs a positive lower bound, got 0"),
    row("parameter-field-typo", {"parameters": {"loss.alpha_a": {"bounds": [1, 2], "lg": True}}}, verdict=ERROR,
        match=r"alpha_a: unknown field\(s\) \['lg'\]"),
    row("unknown-parameter", {"parameters": {"loss.alpha_typo": {"bounds": [1, 2]}}}, verdict=ERROR,
        match=r"search parameter 'loss\.alpha_typo' does not exist in the training config; keys under 'loss'"),
    row("objective-field-typo", {"objective": {"metrics": {"err": 1.0}, "minimise": True}}, verdict=ERROR,
        match=r"search\.objective: unknown field\(s\) \['minimise'\]"),
    row("objective-weight-string", {"objective": {"metrics": {"err": "one"}}}, verdict=ERROR,
        match=r"search\.objective\.metrics\.err: expected a finite number .*got 'one'"),
    row("objective-minimize-string", {"objective": {"metrics": {"err": 1.0}, "minimize": "yes"}}, verdict=ERROR,
        match=r"search\.objective\.minimize: expected true or false, got 'yes'"),
    row("objective-without-metrics", {"objective": {"minimize": True}}, verdict=ERROR,
        match=r"search\.objective\.metrics: name at least one validation metric"),
    row("search-field-typo", {"trails": 3}, verdict=ERROR, match=r"unknown key\(s\) \['trails'\]"),
    row("keep-checkpoints-typo", {"keep_checkpoints": "best"}, verdict=ERROR,
        match=r"search\.keep_checkpoints: expected one of \['weights', 'best_trial', 'none', 'all'\], got 'best'"),
]


@pytest.mark.parametrize("change, verdict, match", SPEC_ROWS)
def test_search_config_values(tmp_path, change, verdict, match):
    from omnidl.search import SearchConfigError, run_search_from_config
    calls = []
    expect(lambda: run_search_from_config(_search_cfg(tmp_path, **change), train_fn=calls.append), verdict, match,
           error=SearchConfigError)
    assert not calls and not (tmp_path / "s").exists()


def test_search_trial_missing_objective_metric_names_it():
    """A trial whose metrics lack an objective metric: the trial fails with the metric and what it had."""
    from omnidl.search import parse_search_spec
    spec = parse_search_spec({"objective": {"metrics": {"val/miou": 1.0}},
                              "parameters": {"loss.a": {"bounds": [0.0, 1.0]}}})
    expect(lambda: spec.scalarise({"val/delta1": 0.5}), ERROR,
           r"objective metric 'val/miou' not among the trial's metrics \['val/delta1'\]", error=KeyError)
    expect(lambda: spec.scalarise({"val/miou": float("nan")}), ERROR, r"'val/miou' is not finite", error=ValueError)


# ---------------------------------------------------------------------------------------------------------------
# §3 8–15  checkpoint=... (train.py / evaluate.py / gyroscope --checkpoint all read through these)
# ---------------------------------------------------------------------------------------------------------------
def _bad_ckpt(tmp, kind):
    from omnidl.engine.checkpoint import save_checkpoint
    p = tmp / "c.pt"
    if kind == "truncated":
        save_checkpoint(p, {"model": {"w": torch.zeros(256, 256)}})
        p.write_bytes(p.read_bytes()[:50_000])
    elif kind == "zero-byte":
        p.write_bytes(b"")
    elif kind == "text":
        p.write_text("not a checkpoint\n")
    elif kind == "list":
        torch.save([1, 2, 3], p)
    elif kind == "no-model":
        torch.save({"foo": 1}, p)
    return p


CKPT_ROWS = [
    row("3-8-missing", "missing", verdict=ERROR, match=r"checkpoint .*c\.pt does not exist"),
    row("3-9-truncated", "truncated", verdict=ERROR, match=r"could not read checkpoint .*c\.pt"),
    row("3-10-zero-byte", "zero-byte", verdict=ERROR, match=r"could not read checkpoint .*c\.pt"),
    row("3-11-text-file", "text", verdict=ERROR, match=r"could not read checkpoint .*c\.pt"),
    row("3-12-pickled-list", "list", verdict=ERROR, match=r"c\.pt.*expected a dict, got list"),
    row("3-13-dict-without-model", "no-model", verdict=ERROR, match=r"c\.pt: no 'model' entry \(keys found: \['foo'\]\)"),
]


@pytest.mark.parametrize("kind, verdict, match", CKPT_ROWS)
def test_checkpoint_files(tmp_path, kind, verdict, match):
    from omnidl.engine.checkpoint import load_checkpoint
    path = _bad_ckpt(tmp_path, kind)
    expect(lambda: load_checkpoint(path), verdict, match)


@pytest.mark.parametrize("name, verdict, match", [
    row("3-14-other-width", "wide", verdict=ERROR,
        match=r"c\.pt does not fit the model \(Sequential\).*size mismatch.*another model config"),
    row("3-15-other-model", "other", verdict=ERROR,
        match=r"c\.pt does not fit the model \(Sequential\).*another model config"),
])
def test_checkpoint_of_another_model(tmp_path, name, verdict, match):
    from omnidl.engine.checkpoint import load_checkpoint, load_model_weights, save_checkpoint
    target = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Linear(8, 2))
    source = (torch.nn.Sequential(torch.nn.Linear(4, 16), torch.nn.Linear(16, 2)) if name == "wide"
              else torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3)))
    save_checkpoint(tmp_path / "c.pt", {"model": source.state_dict()})
    expect(lambda: load_model_weights(target, load_checkpoint(tmp_path / "c.pt"), tmp_path / "c.pt"), verdict, match)
