"""report.html: built from an evaluation folder, self-contained (no network), and it works in a real browser.

The browser tests (``browser`` marker) run the Debian ``chromium`` headless: the page must finish its script
(``data-ready``), report no problem (script errors, failed loads, console errors: the page's own guard counts
them, and Chromium's console log is read too), and a screenshot must show the panorama viewer, the 3-D view and
the first image's panels (pixels checked at the places the page reports for them). Skipped when no Chromium is
installed (``OMNIDL_CHROMIUM`` may name one); ``.ci/run`` installs it.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from omnidl.apps.html_report import collect, write_report
from omnidl.viz import write_ply

CHROMIUM = os.environ.get("OMNIDL_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
#: Chromium's own notes about its software WebGL, not the page's
BROWSER_NOTES = re.compile(r"GL Driver Message|software WebGL|swiftshader|GPU stall", re.I)


def _panorama(h: int, w: int, seed: int) -> np.ndarray:
    """A BGR test panorama: vertical colour bands (so a perspective view of it is not uniform)."""
    rng = np.random.default_rng(seed)
    bands = rng.integers(30, 230, (8, 3)).astype(np.uint8)
    return np.repeat(bands, w // 8, axis=0)[None].repeat(h, axis=0).reshape(h, w, 3)


def make_run(root: Path, names=("room one", "room</script>two"), labels=True, clouds=True) -> Path:
    """An evaluation run folder as ``evaluate`` leaves it (metrics, per-image records, pictures, clouds)."""
    run = root / "run"
    for d in ("images", "inputs", "predictions", "pointclouds"):
        (run / d).mkdir(parents=True, exist_ok=True)
    records = []
    for i, name in enumerate(names):
        stem = f"stem{i}"
        pano = _panorama(64, 128, i)
        cv2.imwrite(str(run / "inputs" / f"{stem}.jpg"), pano)
        cv2.imwrite(str(run / "images" / f"{stem}.png"), np.concatenate([pano, pano[:, ::-1]], 1))
        cv2.imwrite(str(run / "predictions" / f"{stem}_depth.png"),
                    np.linspace(500, 4000, 64 * 128).reshape(64, 128).astype(np.uint16))
        cv2.imwrite(str(run / "predictions" / f"{stem}_semantic.png"), (np.arange(64 * 128) % 14).reshape(64, 128).astype(np.uint8))
        if clouds:
            pts = torch.randn(5000, 3) * torch.tensor([2.0, 1.0, 2.0])
            write_ply(run / "pointclouds" / f"{stem}.ply", pts, torch.rand(5000, 3), frame="gravity_y_up")
        rec = {"index": i, "name": name, "output": stem}
        if labels:
            rec.update(mre=0.1 * (i + 1), delta1=0.9 - 0.1 * i, mae=float("nan") if i == 1 else 0.5)
        records.append(rec)
    metrics = {"mre": 0.15, "delta1": 0.85} if labels else {}
    (run / "metrics.json").write_text(json.dumps({"metrics": metrics, "num_images": len(names), "split": "test",
                                                  "checkpoint": "ckpt.pt", "rotation": {"0": metrics, "10": metrics}}))
    (run / "per_image.json").write_text(json.dumps(records))
    return run


def _page_data(page: str) -> dict:
    m = re.search(r'<script type="application/json" id="report-data">(.*?)</script>', page, re.S)
    return json.loads(m.group(1))


def test_report_is_self_contained_and_holds_the_run(tmp_path):
    run = make_run(tmp_path)
    page = write_report(run).read_text(encoding="utf-8")
    data = _page_data(page)
    assert [im["name"] for im in data["images"]] == ["room one", "room</script>two"]   # "</script>" cannot end the block
    assert data["default_sort"] == "mre" and data["metrics"] == {"mre": 0.15, "delta1": 0.85}
    first = data["images"][0]
    assert first["panel"] == "images/stem0.png" and set(first["layers"]) == {"input", "predicted depth",
                                                                          "predicted semantics"}
    assert first["layers"]["input"].startswith("data:image/jpeg;base64,")
    assert first["cloud"]["n"] == 5000 and len(np.frombuffer(__import__("base64").b64decode(first["cloud"]["xyz"]),
                                                              "<f4")) == 15000
    assert data["images"][1]["values"]["mae"] is None                               # NaN is not valid JSON
    # nothing from a network: every src/href is relative or inline, the 3-D library sits beside the page
    refs = re.findall(r'(?:src|href)="([^"]*)"', page)
    assert refs and all(not re.match(r"\w+://|//", r) for r in refs), refs
    assert (run / "report_assets" / "three.min.js").stat().st_size > 500_000
    assert "MIT" in (run / "report_assets" / "three.LICENSE").read_text()


def test_report_without_labels_or_clouds(tmp_path):
    data = collect(make_run(tmp_path, names=("a",), labels=False, clouds=False))
    assert data["metrics"] == {} and data["default_sort"] is None and data["images"][0]["cloud"] is None


def test_report_needs_an_evaluation_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match="has no metrics.json"):
        write_report(tmp_path)


def test_vendored_viewer_is_pinned():
    import hashlib

    from omnidl.apps.html_report import THREE
    readme = (THREE.parent / "README.md").read_text()
    digest = hashlib.sha256((THREE / "three.min.js").read_bytes()).hexdigest()
    assert digest in readme and "0.159.0" in readme


# --- in a real browser -------------------------------------------------------------------------------------------

def _chromium(args: list[str], profile: Path, timeout: int = 120) -> subprocess.CompletedProcess:
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
             "--disable-component-update", "--no-first-run", f"--user-data-dir={profile}",
             "--enable-unsafe-swiftshader", "--enable-logging=stderr", "--v=0", "--virtual-time-budget=8000",
             "--window-size=1280,1800", "--hide-scrollbars"]
    return subprocess.run([CHROMIUM, *flags, *args], capture_output=True, text=True, timeout=timeout)


def _console_problems(stderr: str) -> list[str]:
    lines = [ln for ln in stderr.splitlines() if ":CONSOLE" in ln]
    return [ln for ln in lines if not BROWSER_NOTES.search(ln)]


@pytest.mark.slow
@pytest.mark.browser
@pytest.mark.skipif(CHROMIUM is None, reason="no chromium installed (apt-get install chromium; .ci/run does)")
@pytest.mark.parametrize("full", [True, False], ids=["labels+clouds", "predictions-only"])
def test_report_in_headless_chromium(tmp_path, full):
    run = make_run(tmp_path, labels=full, clouds=full)
    url = write_report(run).as_uri()
    dom = _chromium(["--dump-dom", url], tmp_path / "profile1")
    assert dom.returncode == 0, dom.stderr[-3000:]
    body = re.search(r"<body([^>]*)>", dom.stdout).group(1)
    attrs = dict(re.findall(r'data-([\w-]+)="([^"]*)"', body))
    assert attrs.get("ready") == "yes", f"the page's script did not finish: {body}\n{dom.stderr[-3000:]}"
    assert attrs.get("problems") == "0", re.search(r'<div id="problems"[^>]*>(.*?)</div>', dom.stdout, re.S).group(1)
    assert not _console_problems(dom.stderr), _console_problems(dom.stderr)
    layout = json.loads(attrs["layout"].replace("&quot;", '"'))

    shot = tmp_path / "report.png"
    res = _chromium([f"--screenshot={shot}", url], tmp_path / "profile2")
    assert res.returncode == 0 and shot.is_file(), res.stderr[-3000:]
    img = cv2.imread(str(shot))

    def crop(name):
        x, y, w, h = layout[name]
        assert w > 100 and h > 40 and y + h <= img.shape[0], f"{name} is not on the first screen: {layout[name]}"
        return img[y + 2:y + h - 2, x + 2:x + w - 2].astype(np.float32)

    pano = crop("pano")                       # a perspective view of the colour bands: several colours, no black
    assert pano.std(axis=(0, 1)).max() > 15 and (pano.max(-1) < 10).mean() < 0.01
    panel = crop("panel")                     # the first card's panels
    assert panel.std() > 15
    cloud = crop("cloud")                     # points over the dark background (0x22)
    drawn = (np.abs(cloud - 0x22).max(-1) > 30).mean()
    assert (drawn > 0.01) if full else (drawn < 0.01), drawn
    artifacts = os.environ.get("OMNIDL_REPORT_SCREENSHOT")
    if artifacts:                             # keep the picture to look at
        shutil.copy(shot, artifacts)
