"""Hypothesis properties of the output policy (issue 48 item 1/5): generated file names (unicode, spaces, one stem
with several extensions, names differing only in case) and output folders (equal to / inside / containing / beside
the input folder), for the writer helpers (omnidl.utils.outputs) and the reproject and synth commands.

Invariants: every input byte is kept (each input is hashed before and after); a previous output is never
replaced without the overwrite option; outputs of colliding inputs never land on one file.
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

SETTINGS = dict(deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])

#: stems: ASCII, spaces, accents, CJK, emoji; case variants come from the draws below
STEM = st.text(alphabet=st.sampled_from(list("aAbB xX_-.éÉ部屋😀1")), min_size=1, max_size=6).filter(
    lambda s: s.strip(" .") == s and s not in (".", "..") and not s.startswith("-"))
EXT = st.sampled_from([".png", ".jpg", ".PNG", ".tif", ""])
RELATION = st.sampled_from(["equal", "inside", "containing", "beside"])


def _hash(paths) -> dict[Path, str]:
    return {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in paths}


def _layout(root: Path, relation: str) -> tuple[Path, Path]:
    """``(input folder, output folder)`` for ``relation``."""
    return {"equal": (root / "in", root / "in"), "inside": (root / "in", root / "in" / "out"),
            "containing": (root / "top" / "in", root / "top"), "beside": (root / "in", root / "out")}[relation]


def _names(draw_names: list[tuple[str, str, bool]]) -> list[str]:
    out, seen = [], set()
    for stem, ext, upper in draw_names:
        name = (stem.upper() if upper else stem) + ext
        if name not in seen and name not in (".", ".."):
            seen.add(name)
            out.append(name)
    return out


NAMES = st.lists(st.tuples(STEM, EXT, st.booleans()), min_size=1, max_size=6).map(_names).filter(bool)


@settings(max_examples=50, **SETTINGS)
@given(names=NAMES)
def test_unique_stems_are_unique_stable_and_keep_free_names(names):
    from omnidl.utils.outputs import unique_stems
    stems = unique_stems(names)
    assert len(stems) == len(names) and len({s.casefold() for s in stems}) == len(stems)
    assert unique_stems(list(names)) == stems
    plain = [Path(n).stem or n for n in names]
    for n, p, s in zip(names, plain, stems):
        if sum(q.casefold() == p.casefold() for q in plain) == 1:
            assert s == p


@settings(max_examples=50, **SETTINGS)
@given(names=NAMES, relation=RELATION, overwrite=st.booleans(), suffix=st.sampled_from(["", "_depth", "_x"]),
       ext=st.sampled_from([".png", ".jpg"]))
def test_a_writer_under_the_policy_never_loses_an_input_or_an_old_output(names, relation, overwrite, suffix, ext):
    """A writer maps each input to ``<unique stem><suffix><ext>`` in the output folder, guarded; it runs twice.
    Inputs are never changed; the first run's outputs survive the second unless ``overwrite``."""
    from omnidl.utils.outputs import OutputExistsError, atomic_write_bytes, guard_outputs, unique_stems
    with tempfile.TemporaryDirectory() as tmp:
        in_dir, out_dir = _layout(Path(tmp), relation)
        in_dir.mkdir(parents=True)
        out_dir.mkdir(parents=True, exist_ok=True)
        inputs = [in_dir / n for n in names]
        for i, p in enumerate(inputs):
            p.write_bytes(f"input {i} {p.name}".encode())
        before = _hash(inputs)

        def write(tag: str) -> bool:
            outs = [out_dir / f"{s}{suffix}{ext}" for s in unique_stems(inputs)]
            try:
                guard_outputs(outs, [in_dir], overwrite=overwrite)
            except (OutputExistsError, ValueError):
                return False
            for o, p in zip(outs, inputs):
                atomic_write_bytes(o, f"{tag} of {p.name}".encode())
            return True

        first = write("first")
        firsts = {p: p.read_bytes() for p in out_dir.iterdir() if p.is_file() and p not in before}
        second = write("second")
        assert _hash(inputs) == before                                    # never a lost or changed input byte
        if first and not overwrite:
            assert not second and all(p.read_bytes() == b for p, b in firsts.items())
        if first:   # one output file per input: no two inputs collided on one name
            assert len([p for p in out_dir.iterdir() if p.is_file() and p not in before]) >= len(inputs)


# ---------------------------------------------------------------------------------------------------- reproject

def _run(main, argv) -> int:
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        try:
            return main([str(a) for a in argv])
        except SystemExit as e:
            return 0 if e.code in (0, None) else 2


REPRO_NAME = st.tuples(STEM.filter(lambda s: "😀" not in s), st.sampled_from([".png", ".PNG"]))


@settings(max_examples=25, **SETTINGS)
@example(src=("a b", ".png"), relation="equal", target="src", overwrite=False, mask=False)
@given(src=REPRO_NAME, relation=RELATION, target=st.sampled_from(["src", "other", "new", "src-case"]),
       overwrite=st.booleans(), mask=st.booleans())
def test_reproject_never_replaces_its_source_or_an_older_file(src, relation, target, overwrite, mask):
    from omnidl.apps.reproject import main
    with tempfile.TemporaryDirectory() as tmp:
        in_dir, out_dir = _layout(Path(tmp), relation)
        in_dir.mkdir(parents=True)
        out_dir.mkdir(parents=True, exist_ok=True)
        src_path = in_dir / (src[0] + src[1])
        ok, buf = cv2.imencode(".png", (np.arange(16 * 8 * 3) % 251).reshape(8, 16, 3).astype(np.uint8))
        src_path.write_bytes(buf.tobytes())
        other = out_dir / "previous.png"
        other.write_bytes(b"a previous output")
        out = {"src": src_path, "other": other, "new": out_dir / f"{src[0]} r.png",
               "src-case": in_dir / (src[0].swapcase() + src[1])}[target]
        existed = out.exists()
        watched = [src_path, other]
        before = _hash(watched)
        argv = ["--src", src_path, "--dst-camera", "pinhole", "--out", out]
        if mask:
            argv += ["--mask-out", out_dir / "mask.png"]
        if overwrite:
            argv.append("--overwrite")
        rc = _run(main, argv)
        after = _hash(watched)
        assert after[src_path] == before[src_path]                         # the source is never touched
        if not overwrite:
            assert after[other] == before[other]                           # an old output needs --overwrite
        if rc == 0:
            assert out.is_file() and not same(out, src_path) and (overwrite or not existed)


def same(a: Path, b: Path) -> bool:
    try:
        return a.samefile(b)
    except OSError:
        return False


# ---------------------------------------------------------------------------------------------------- synth

@settings(max_examples=8, **SETTINGS)
@given(cam_stem=STEM.filter(lambda s: "😀" not in s), relation=RELATION, overwrite=st.booleans(),
       foreign=st.sampled_from([None, "contact_sheet.png", "notes.txt"]))
@example(cam_stem="cam", relation="equal", overwrite=False, foreign="contact_sheet.png")
@example(cam_stem="cam", relation="containing", overwrite=True, foreign="notes.txt")
def test_synth_never_replaces_its_camera_file_or_a_foreign_file(cam_stem, relation, overwrite, foreign):
    from omnidl.apps.synth import main
    from omnidl.cameras import resolve_camera
    with tempfile.TemporaryDirectory() as tmp:
        in_dir, out_dir = _layout(Path(tmp), relation)
        in_dir.mkdir(parents=True)
        cam = in_dir / f"{cam_stem}.yaml"
        shutil.copyfile(Path(__file__).resolve().parents[2] / "configs" / "camera" / "equirect.yaml", cam)
        resolve_camera(str(cam), 32, 16)
        watched = [cam]
        if foreign:
            out_dir.mkdir(parents=True, exist_ok=True)
            (out_dir / foreign).write_bytes(b"someone else's file")
            watched.append(out_dir / foreign)
        before = _hash(watched)
        argv = ["--camera", cam, "--n", 1, "--out", out_dir, "--width", 32, "--height", 16, "--format", "horizonnet",
                "--contact-sheet", 1] + (["--overwrite"] if overwrite else [])
        rc = _run(main, argv)
        after = _hash([p for p in watched if p.exists()])
        assert after.get(cam) == before[cam]                               # the camera file is never touched
        if foreign and not overwrite:
            assert after.get(out_dir / foreign) == before[out_dir / foreign]
        if foreign == "notes.txt":
            assert after.get(out_dir / foreign) == before[out_dir / foreign]   # not ours: kept even with --overwrite
        if rc == 0:
            assert (out_dir / "synth.json").is_file()
