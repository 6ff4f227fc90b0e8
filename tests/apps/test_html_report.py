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


#: a 4 x 5 m room, camera 1.5 m above the floor (layout frame: z up); the ground truth is the same room shifted
ROOM = {"ok": True, "corners_2d": [[2, -2], [2, 3], [-2, 3], [-2, -2]], "h_floor": -1.5, "h_ceiling": 1.3,
        "floor_corners": [[2, -2, -1.5], [2, 3, -1.5], [-2, 3, -1.5], [-2, -2, -1.5]],
        "ceiling_corners": [[2, -2, 1.3], [2, 3, 1.3], [-2, 3, 1.3], [-2, -2, 1.3]]}
ROOM_GT = {"floor_corners": [[2.2, -2, -1.5], [2.2, 3, -1.5], [-2, 3, -1.5], [-2, -2, -1.5]],
           "ceiling_corners": [[2.2, -2, 1.3], [2.2, 3, 1.3], [-2, 3, 1.3], [-2, -2, 1.3]]}


def make_run(root: Path, names=("room one", "room</script>two"), labels=True, clouds=True, layouts=False) -> Path:
    """An evaluation run folder as ``evaluate`` leaves it (metrics, per-image records, pictures, clouds; with
    ``layouts`` the layout hooks' ``postprocess.jsonl``: a predicted layout for every image, ground truth for the
    first, a failed prediction for a third sample)."""
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
    if layouts:
        stems = [f"stem{i}" for i in range(len(names))]
        lines = [{"names": stems, "layout": [ROOM] * len(names), "layout_gt": [ROOM_GT] + [None] * (len(names) - 1)},
                 {"names": ["other"], "layout": [{"ok": False, "reason": "no corners"}]}]
        (run / "postprocess.jsonl").write_text("\n".join(json.dumps(x) for x in lines) + "\nnot json\n")
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


def test_layout_wireframes_are_embedded_in_the_clouds_frame(tmp_path, capsys):
    """Issue 49: the 3-D view gets the predicted and the ground-truth layout of each image, as segments in the
    point clouds' y-up frame (layout (x, y, z) -> (x, z, -y)): 4 ceiling + 4 floor + 4 vertical edges."""
    data = collect(make_run(tmp_path, layouts=True))
    first, second = data["images"][0]["layout"], data["images"][1]["layout"]
    assert set(first) == {"pred", "gt"} and set(second) == {"pred"}
    seg = np.asarray(first["pred"]).reshape(-1, 2, 3)
    assert seg.shape == (12, 2, 3)
    np.testing.assert_allclose(seg[0], [[2, 1.3, 2], [2, 1.3, -3]])          # ceiling edge, y up, -z forward
    np.testing.assert_allclose(seg[8], [[2, -1.5, 2], [2, 1.3, 2]])          # vertical edge at corner 0
    assert np.asarray(first["gt"]).reshape(-1, 2, 3)[0, 0, 0] == 2.2
    assert "postprocess.jsonl:3: skipped, not JSON" in capsys.readouterr().err


def test_layout_only_run_has_a_3d_view(tmp_path):
    """A layout model writes no point cloud: the 3-D view still lists the image, for its wireframes."""
    run = make_run(tmp_path, names=("a",), clouds=False, layouts=True)
    page = write_report(run).read_text(encoding="utf-8")
    im = _page_data(page)["images"][0]
    assert im["cloud"] is None and len(im["layout"]["pred"]) == 12 * 6
    js = (Path(__import__("omnidl.apps.html_report", fromlist=["HERE"]).HERE) / "report.js").read_text()
    assert "im.cloud || im.layout" in js and "LineSegments" in js


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
    run = make_run(tmp_path, names=("room one", "room</script>two", "<!--<script>x"), labels=full, clouds=full,
                   layouts=True)
    url = write_report(run).as_uri()
    dom = _chromium(["--dump-dom", url], tmp_path / "profile1")
    assert dom.returncode == 0, dom.stderr[-3000:]
    body = re.search(r"<body([^>]*)>", dom.stdout).group(1)
    attrs = dict(re.findall(r'data-([\w-]+)="([^"]*)"', body))
    assert attrs.get("ready") == "yes", f"the page's script did not finish: {body}\n{dom.stderr[-3000:]}"
    assert attrs.get("problems") == "0", re.search(r'<div id="problems"[^>]*>(.*?)</div>', dom.stdout, re.S).group(1)
    assert not _console_problems(dom.stderr), _console_problems(dom.stderr)
    layout = json.loads(attrs["layout"].replace("&quot;", '"'))
    # the first image's predicted and ground-truth layouts are in the 3-D view (12 segments each)
    assert json.loads(attrs["wireframes"].replace("&quot;", '"')) == {"pred": 12, "gt": 12}

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
    assert drawn > 0.01, drawn
    b, g, r = cloud[..., 0], cloud[..., 1], cloud[..., 2]
    green = ((g > 180) & (r < 120) & (b < 160)).sum()       # predicted wireframe (#33ff66)
    orange = ((r > 200) & (g > 100) & (g < 180) & (b < 80)).sum()   # ground truth (#ff8c1a)
    assert green > 50 and orange > 50, (green, orange)
    artifacts = os.environ.get("OMNIDL_REPORT_SCREENSHOT")
    if artifacts:                             # keep the picture to look at
        shutil.copy(shot, artifacts)


# --- issue 48: user strings are text, never markup; a report is never overwritten -------------------------------------

HOSTILE = ["</script><script>alert(1)</script>", "<!--<script>", "</SCRIPT >", "a\" onerror=\"x", "it's & <b>",
           "\u2028\u2029", "é 😀 \u0000", "]]><![CDATA[", "<img src=x onerror=alert(1)>"]


def _tags(page: str) -> list[str]:
    """Every piece of markup of the page, in order."""
    return re.findall(r"<[!/?]?[A-Za-z][^>]*>|<!--", page)


def _hostile_run(root: Path, text: str, folder: str = "run") -> Path:
    run = root / folder
    run.mkdir(parents=True)
    (run / "metrics.json").write_text(json.dumps({"metrics": {text: 0.5, "mre": 0.1}, "split": text,
                                                  "checkpoint": text, "rotation": {text: {text: 1.0}}}))
    (run / "per_image.json").write_text(json.dumps([{"index": 0, "name": text, "output": text, text: 0.25},
                                                    {"index": 1, "name": "plain", "output": "plain"}]))
    return run


_BENIGN: list[str] = []


def _benign_tags(tmp: Path) -> list[str]:
    if not _BENIGN:
        _BENIGN.extend(_tags(write_report(_hostile_run(tmp, "plain text", "benign")).read_text(encoding="utf-8")))
    return _BENIGN


@pytest.mark.parametrize("text", HOSTILE)
def test_hostile_strings_stay_data(tmp_path, text):
    """File names, config values, metric and sample names with markup in them add no markup to the page, cannot
    end the data block, and come back unchanged from the page's JSON."""
    run = _hostile_run(tmp_path, text)
    page = write_report(run).read_text(encoding="utf-8")
    assert _tags(page) == _benign_tags(tmp_path / "b")
    block = re.search(r'<script type="application/json" id="report-data">(.*?)</script>', page, re.S).group(1)
    assert not re.search("[<>&\u2028\u2029]", block)
    data = json.loads(block)
    assert data["images"][0]["name"] == text and data["split"] == text and data["checkpoint"] == text
    assert text in data["metrics"] and data["images"][0]["values"][text] == 0.25


def test_run_folder_name_is_escaped_in_the_title(tmp_path):
    name = "<i onmouseover='x'>\"q\" & y<!--"                       # a folder name: no "/"
    page = write_report(_hostile_run(tmp_path, "plain", folder=name)).read_text(encoding="utf-8")
    import html as _html
    title = re.search(r"<title>(.*?)</title>", page, re.S).group(1)
    assert "<" not in title and _html.unescape(title) == f"omnidl evaluation: {name}"


def test_hostile_strings_property(tmp_path_factory):
    """Hypothesis: any text (markup characters, quotes, entities, line separators, any unicode) as sample name,
    metric name, split and checkpoint leaves the page's markup unchanged and round-trips through its JSON."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    benign = _benign_tags(tmp_path_factory.mktemp("benign"))
    alphabet = st.sampled_from(list("<>/&'\"!-=[] ") + ["script", "SCRIPT", "<!--", "-->", "\u2028", "\u2029",
                                                         "&amp;", "\\u003c"]) | st.characters()
    texts = st.lists(alphabet, min_size=1, max_size=12).map("".join)

    @settings(max_examples=25, deadline=None, derandomize=True)
    @given(texts)
    def check(text):
        run = _hostile_run(tmp_path_factory.mktemp("h"), text)
        data = collect(run)
        page = __import__("omnidl.apps.html_report", fromlist=["render_page"]).render_page(data, run.name)
        assert _tags(page) == benign
        block = re.search(r'<script type="application/json" id="report-data">(.*?)</script>', page, re.S).group(1)
        assert json.loads(block) == data and data["images"][0]["name"] == text
    check()


def test_stems_that_are_paths_read_no_files(tmp_path, capsys):
    run = make_run(tmp_path, names=("a",))
    secret = tmp_path / "secret.jpg"
    cv2.imwrite(str(secret), _panorama(8, 16, 3))
    (run / "per_image.json").write_text(json.dumps([{"index": 0, "name": "a", "output": "../../secret"}]))
    data = collect(run)
    assert data["images"][0]["layers"] == {} and data["images"][0]["panel"] is None
    assert "is not a plain file name" in capsys.readouterr().err


def test_panel_links_are_url_encoded(tmp_path):
    run = make_run(tmp_path, names=("a",))
    (run / "images" / "stem0.png").rename(run / "images" / "a#b?c.png")
    (run / "per_image.json").write_text(json.dumps([{"index": 0, "name": "a", "output": "a#b?c"}]))
    assert collect(run)["images"][0]["panel"] == "images/a%23b%3Fc.png"


def test_report_never_overwrites_without_the_option(tmp_path, capsys):
    from omnidl.apps.html_report.__main__ import main
    run = make_run(tmp_path, names=("a",), clouds=False)
    (run / "report.html").write_text("my page")
    assert main([str(run)]) == 2
    err = capsys.readouterr().err
    assert "report.html already exists" in err and "--overwrite" in err
    assert (run / "report.html").read_text() == "my page" and not (run / "report_assets").exists()
    assert main([str(run), "--overwrite"]) == 0
    assert "omnidl evaluation" in (run / "report.html").read_text()
    # the vendored library beside it is rewritten only when it differs (a user's file of that name is kept)
    (run / "report.html").unlink()
    (run / "report_assets" / "three.min.js").write_text("mine")
    assert main([str(run)]) == 2 and (run / "report_assets" / "three.min.js").read_text() == "mine"
    assert "three.min.js already exists" in capsys.readouterr().err
