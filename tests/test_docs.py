"""The documentation cannot rot: its runnable example runs, and every name it gives exists.

* The code blocks of ``docs/extending.md`` marked with a ``<!-- runnable -->`` line right before the
  fence (the worked example "adding a camera model") run in order as one script, in a fresh Python
  process (the example registers a camera type; the test process's registry stays as it is).
* Every repository path (``omnidl/...``, ``configs/...``, ``tests/...``, ``benchmarks/...``,
  ``docs/...``; ``{a,b}`` alternatives and ``*`` globs expanded, ``<placeholder>`` paths skipped),
  every dotted name ``omnidl.<package>.<name>`` (a module, or an attribute of one), every
  ``from omnidl.<package> import a, b`` line and every ``python -m <module>`` command named in
  ``README.md`` and ``docs/*.md`` exists, every config choice of a ``train.py``/``evaluate.py`` command
  (``model=fredsnet``, ``+search=...``) is a file of ``configs/``, and every in-page link
  ``[...](#anchor)`` meets a heading.
"""
from __future__ import annotations

import importlib
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
EXAMPLE = ROOT / "docs" / "extending.md"

RUNNABLE = re.compile(r"^<!-- runnable -->\n```python\n(.*?)^```", re.S | re.M)
PATH = re.compile(r"(?<![\w./-])(?:omnidl|configs|tests|benchmarks|docs)/[\w./{},*<>-]*")
DOTTED = re.compile(r"(?<![\w./-])omnidl\.[\w.{},/]*\w\}?")
FROM_IMPORT = re.compile(r"^\s*from (omnidl[\w.]*) import ([^#\n(;]+)", re.M)
PYTHON_M = re.compile(r"python -m ([\w.]+)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)
#: ``group=option`` (or ``+search=option``) of a ``train.py``/``evaluate.py`` command line
GROUP_CHOICE = re.compile(r"(?<![\w.+/])\+?(model|data|camera|loss|metrics|optim|sched|trainer|viz|experiment|search)"
                          r"=([\w,-]+)")


def _ids(paths: list[Path]) -> list[str]:
    return [str(p.relative_to(ROOT)) for p in paths]


def _expand(text: str) -> list[str]:
    """Every alternative of ``{a,b}`` groups: ``x/{a,b}.py`` -> ``[x/a.py, x/b.py]``."""
    m = re.search(r"\{([^{}]*)\}", text)
    if m is None:
        return [text]
    return [out for alt in m.group(1).split(",")
            for out in _expand(text[:m.start()] + alt.strip() + text[m.end():])]


def _resolve(name: str) -> bool:
    """``name`` (``omnidl.a.b.c``) is an importable module or an attribute chain of one."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError as exc:
            if exc.name is not None and not ".".join(parts[:i]).startswith(exc.name):
                raise                                   # a broken import inside an existing module
            continue
        for j, attr in enumerate(parts[i:], start=i):
            if hasattr(obj, attr):
                obj = getattr(obj, attr)
                continue
            try:                                        # a submodule not imported by its package
                obj = importlib.import_module(".".join(parts[:j + 1]))
            except ModuleNotFoundError:
                return False
        return True
    return False


@pytest.mark.slow
def test_extending_example_runs(tmp_path):
    blocks = RUNNABLE.findall(EXAMPLE.read_text(encoding="utf-8"))
    assert len(blocks) >= 5, "docs/extending.md lost its runnable blocks (<!-- runnable --> before ```python)"
    script = "\n".join(blocks)
    for step in ("register_camera", "ProjectedConv2d", "SyntheticCameraDataset", "reproject", "estimate_layout"):
        assert step in script, f"the worked example no longer shows {step}"
    path = tmp_path / "extending_example.py"
    path.write_text(script, encoding="utf-8")
    res = subprocess.run([sys.executable, str(path)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, f"docs/extending.md example failed:\n{res.stdout[-3000:]}\n{res.stderr[-6000:]}"


@pytest.mark.parametrize("doc", DOCS, ids=_ids(DOCS))
def test_named_paths_exist(doc):
    missing = []
    for m in PATH.finditer(doc.read_text(encoding="utf-8")):
        token = m.group(0).rstrip(".,:;")
        if "<" in token or ">" in token:
            continue                                    # a placeholder such as tests/cameras/test_<model>.py
        for path in _expand(token):
            if "*" in path:
                found = any(ROOT.glob(path.rstrip("/")))
            else:
                p = ROOT / path
                found = p.exists() or p.with_suffix(".py").exists()
            if not found:
                missing.append(path)
    assert not missing, f"{doc.name} names paths that do not exist: {sorted(set(missing))}"


@pytest.mark.parametrize("doc", DOCS, ids=_ids(DOCS))
def test_named_modules_and_objects_exist(doc):
    text = doc.read_text(encoding="utf-8")
    names = set()
    for m in DOTTED.finditer(text):
        token = m.group(0)
        # "omnidl.losses.depth/segmentation/joint" lists alternatives like {depth,segmentation,joint}
        token = ".".join("{" + p.replace("/", ",") + "}" if "/" in p else p for p in token.split("."))
        names.update(n for n in _expand(token) if not n.endswith((".py", ".pth", ".md", ".yaml")))
    for m in FROM_IMPORT.finditer(text):
        for item in m.group(2).split(","):
            item = item.strip().rstrip("\\").split(" as ")[0].strip()
            if item and item != "*":
                names.add(f"{m.group(1)}.{item}")
    missing = sorted(n for n in names if not _resolve(n))
    assert not missing, f"{doc.name} names modules or objects that do not exist: {missing}"


@pytest.mark.parametrize("doc", DOCS, ids=_ids(DOCS))
def test_python_m_commands_exist(doc):
    missing = []
    for m in PYTHON_M.finditer(doc.read_text(encoding="utf-8")):
        base = ROOT.joinpath(*m.group(1).split("."))
        module = base.with_suffix(".py")
        if module.is_file():
            if "__main__" not in module.read_text(encoding="utf-8"):
                missing.append(f"{m.group(1)} (no __main__ block)")
        elif not (base / "__main__.py").is_file():
            missing.append(m.group(1))
    assert not missing, f"{doc.name} gives `python -m` commands whose module does not exist: {missing}"


@pytest.mark.parametrize("doc", DOCS, ids=_ids(DOCS))
def test_in_page_links_meet_a_heading(doc):
    text = FENCE.sub("", doc.read_text(encoding="utf-8"))
    # GitHub's anchors: lower case, punctuation dropped (letters, digits, "_", "-" and spaces kept), spaces -> "-"
    anchors = {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-")
               for h in re.findall(r"^#{1,6} (.+)$", text, re.M)}
    broken = sorted(set(re.findall(r"\]\(#([^)]+)\)", text)) - anchors)
    assert not broken, f"{doc.name} links to headings that do not exist: {broken}"


@pytest.mark.parametrize("doc", DOCS, ids=_ids(DOCS))
def test_command_line_config_choices_exist(doc):
    missing = []
    for line in doc.read_text(encoding="utf-8").splitlines():
        if not re.search(r"\b(train|evaluate)\.py\b", line):
            continue
        for group, values in GROUP_CHOICE.findall(line):
            for value in values.split(","):
                # *_best loss configs are written by a search (git-ignored); `-m` sweeps list several values
                if not value.endswith("_best") and not (ROOT / "configs" / group / f"{value}.yaml").is_file():
                    missing.append(f"{group}={value}")
    assert not missing, f"{doc.name} gives command lines with config choices that do not exist: {sorted(set(missing))}"
