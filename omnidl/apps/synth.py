"""Writer CLI: ``python -m omnidl.apps.synth --camera noncentral_pano --n 100 --out datasets/synth_nc``.

Renders ``n`` procedural rooms and writes them in a real dataset's on-disk format (see
:mod:`omnidl.synth.export`), resumable (finished samples are skipped), with atomic writes, a progress
bar and a contact sheet PNG (RGB | depth | semantics | layout wireframe) of the first samples.

``--out/synth.json`` records the settings that made the dataset (camera, size, seed, split, format, ...).
Running again into the same ``--out`` resumes or extends it (more samples, another ``--start``) only with
the same settings; other settings, or sample files with no ``synth.json``, are an error instead of a
silently mixed dataset. ``--overwrite`` deletes the samples this writer made there and starts again.

Output policy (:mod:`omnidl.utils.outputs`): one writer per ``--out`` at a time (``--out/.omnidl.lock``: a second
process stops with a message naming the first); the camera file given to ``--camera`` is never written over or
deleted, not even with ``--overwrite``; a ``contact_sheet.png`` in a folder this writer did not make is replaced
only with ``--overwrite``.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import torch
from tqdm import tqdm

from omnidl.cameras import resolve_camera
from omnidl.synth import SPLITS, render_sample
from omnidl.synth.export import FORMATS, expected_files, sample_name, write_contact_sheet, write_sample
from omnidl.utils.io import atomic_write_json
from omnidl.utils.outputs import RunLock, RunLockedError, guard_outputs, same_file

MANIFEST = "synth.json"
#: glob of the sample names :func:`omnidl.synth.export.sample_name` gives, per format
NAME_GLOBS = {"noncentral": "SYN?????_R?????", "stanford": "camera_*_synthroom_*_frame_equirectangular_domain",
              "horizonnet": "synth_?????"}
#: the arguments that change what a sample looks like (``--n``/``--start`` only say which samples)
SETTINGS = ("camera", "format", "width", "height", "rc", "seed", "split", "rotation", "max_tilt", "manhattan_ratio",
            "furniture", "shadows", "area")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m omnidl.apps.synth", description=__doc__.split("\n\n")[0])
    p.add_argument("--camera", default="noncentral_pano",
                   help="camera: a configs/camera name, a YAML path or a registered type (default noncentral_pano)")
    p.add_argument("--n", type=int, default=100, help="number of samples")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--format", choices=FORMATS, default=None,
                   help="on-disk format (default: noncentral for non-central cameras, else stanford)")
    p.add_argument("--width", type=int, default=None)
    p.add_argument("--height", type=int, default=None)
    p.add_argument("--rc", type=float, default=None, help="non-central panorama radius (m)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--split", choices=sorted(SPLITS), default="train")
    p.add_argument("--start", type=int, default=0, help="index of the first sample")
    p.add_argument("--rotation", choices=["upright", "random"], default="upright")
    p.add_argument("--max-tilt", type=float, default=30.0, help="degrees, with --rotation random")
    p.add_argument("--manhattan-ratio", type=float, default=0.7)
    p.add_argument("--no-furniture", action="store_true")
    p.add_argument("--shadows", action="store_true", help="box shadows from the lights (slower)")
    p.add_argument("--area", default="area_1", help="area folder for --format stanford")
    p.add_argument("--contact-sheet", type=int, default=6, help="samples on contact_sheet.png (0 = none)")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--overwrite", action="store_true",
                   help=f"delete the samples (and {MANIFEST}) a previous run wrote into --out, then write anew")
    return p.parse_args(argv)


def check_args(args: argparse.Namespace) -> None:
    """``SystemExit`` naming the flag, its value and what was expected, before any work."""
    if args.n < 0:
        raise SystemExit(f"--n must be >= 0, got {args.n}")
    if args.start < 0:
        raise SystemExit(f"--start must be >= 0, got {args.start}")
    if (args.width is None) != (args.height is None):
        raise SystemExit(f"give both --width and --height or neither (got --width {args.width}, "
                         f"--height {args.height})")
    for flag in ("width", "height"):
        v = getattr(args, flag)
        if v is not None and v < 2:
            raise SystemExit(f"--{flag} must be an image size >= 2 pixels, got {v}")
    if not 0.0 <= args.manhattan_ratio <= 1.0:
        raise SystemExit(f"--manhattan-ratio is a probability in [0, 1], got {args.manhattan_ratio}")
    if not 0.0 <= args.max_tilt <= 90.0:
        raise SystemExit(f"--max-tilt must be in [0, 90] degrees, got {args.max_tilt}")
    if args.threads is not None and args.threads < 1:
        raise SystemExit(f"--threads must be >= 1, got {args.threads}")
    if args.contact_sheet < 0:
        raise SystemExit(f"--contact-sheet must be >= 0 (0: no contact sheet), got {args.contact_sheet}")
    if not re.fullmatch(r"area_\w+", args.area):
        raise SystemExit(f"--area {args.area!r}: Stanford2D3DS area folders are named area_<id> (e.g. area_1, "
                         "area_5a), which is what the loader reads")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise SystemExit(f"--out {out} is an existing file; expected a folder (new or made by this writer)")


def settings_of(args: argparse.Namespace, cam, fmt: str, rc: float) -> dict:
    """What made the samples (see :data:`SETTINGS`): the camera as given, its resolved size, and the options."""
    return {"camera": str(args.camera), "format": fmt, "width": int(cam.width), "height": int(cam.height),
            "rc": round(rc, 6), "seed": args.seed, "split": args.split, "rotation": args.rotation,
            "max_tilt": float(args.max_tilt) if args.rotation == "random" else None,
            "manhattan_ratio": float(args.manhattan_ratio), "furniture": not args.no_furniture,
            "shadows": bool(args.shadows), "area": args.area if fmt == "stanford" else None}


def existing_samples(out: Path) -> list[Path]:
    """Sample files of any format this writer produces already in ``out``."""
    found: set[Path] = set()
    for fmt, pattern in NAME_GLOBS.items():
        for f in expected_files(Path("."), fmt, pattern, "area_*"):
            found.update(out.glob(f.as_posix()))
    return sorted(found)


def check_out(out: Path, settings: dict, overwrite: bool, inputs: list[Path] = ()) -> None:
    """Refuse to mix datasets: ``out`` must be new, or hold a dataset this writer made with ``settings``.
    ``inputs``: files the run reads (the camera file), never deleted or replaced."""
    manifest = out / MANIFEST
    try:   # the manifest and the contact sheet: never an input; the sheet of a foreign folder only with --overwrite
        guard_outputs([manifest], inputs, overwrite=True)
        sheet_is_ours = manifest.exists()
        guard_outputs([out / "contact_sheet.png"], inputs, overwrite=overwrite or sheet_is_ours)
    except (FileExistsError, ValueError) as e:
        raise SystemExit(f"--out {out}: {e}") from None
    if overwrite:
        removed = [f for f in existing_samples(out) if not any(same_file(f, i) for i in inputs)]
        for f in removed + [manifest, out / "contact_sheet.png"]:
            f.unlink(missing_ok=True)
        if removed:
            print(f"--overwrite: removed {len(removed)} sample files from {out}", file=sys.stderr)
        return
    if manifest.exists():
        try:
            saved = json.loads(manifest.read_text())
            saved = saved.get("settings", saved) if isinstance(saved, dict) else None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise SystemExit(f"{manifest} cannot be read ({exc}); it records which settings made the dataset in "
                             f"{out}. Use another --out, or --overwrite to start that folder again") from None
        if not isinstance(saved, dict):
            raise SystemExit(f"{manifest} does not hold the writer's settings; use another --out or --overwrite")
        diff = [f"{k}: {saved.get(k)!r} there, {settings[k]!r} now" for k in SETTINGS if saved.get(k) != settings[k]]
        if diff:
            raise SystemExit(f"--out {out} already holds a dataset made with other settings ({'; '.join(diff)}); "
                             "adding to it would mix two datasets. Use another --out, the same settings (to resume "
                             "or extend it), or --overwrite to replace its samples")
        return
    found = existing_samples(out)
    if found:
        raise SystemExit(f"--out {out} already holds {len(found)} sample files (e.g. {found[0]}) but no {MANIFEST}, "
                         "so the settings that made them are unknown and adding to them could mix two datasets. "
                         "Use another --out, or --overwrite to replace them")


def main(argv=None) -> int:
    args = parse_args(argv)
    check_args(args)
    if args.threads:
        torch.set_num_threads(args.threads)
    fields = {}
    if args.rc is not None:
        fields["rc"] = args.rc
    try:
        cam = resolve_camera(args.camera, args.width, args.height, **fields)
    except (ValueError, TypeError, FileNotFoundError, KeyError) as exc:
        raise SystemExit(f"--camera {args.camera!r}: {exc}") from None
    fmt = args.format or ("stanford" if getattr(cam, "central", True) else "noncentral")
    if fmt in ("noncentral", "horizonnet") and args.rotation != "upright":
        raise SystemExit(f"--format {fmt} needs --rotation upright (the dataset's panoramas are gravity-aligned)")
    out = Path(args.out)
    rc = float(getattr(cam, "rc", getattr(getattr(cam, "base", None), "rc", 0.0)) or 0.0)
    settings = settings_of(args, cam, fmt, rc)
    inputs = [Path(args.camera)] if Path(args.camera).is_file() else []
    created = not out.exists()
    try:
        with RunLock(out, "synth writer"):
            return _write(args, cam, fmt, rc, out, settings, inputs)
    except RunLockedError as e:
        raise SystemExit(str(e)) from None
    except SystemExit:
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()          # a refused run leaves no folder behind
        raise


def _write(args: argparse.Namespace, cam, fmt: str, rc: float, out: Path, settings: dict, inputs: list[Path]) -> int:
    """:func:`main` once ``out`` is locked."""
    check_out(out, settings, args.overwrite, inputs)
    if not (out / MANIFEST).exists():  # (an existing one holds these settings: check_out compared them)
        atomic_write_json(out / MANIFEST, {"writer": "python -m omnidl.apps.synth", "settings": settings})
    sheet, skipped = [], 0
    for index in tqdm(range(args.start, args.start + args.n), desc=f"synth -> {fmt}", unit="img"):
        name = sample_name(fmt, index, rc)
        files = expected_files(out, fmt, name, args.area)
        want_sheet = len(sheet) < args.contact_sheet
        if all(f.exists() for f in files) and not want_sheet:
            skipped += 1
            continue
        sample = render_sample(cam, args.seed, args.split, index, rotation=args.rotation, max_tilt_deg=args.max_tilt,
                               manhattan_ratio=args.manhattan_ratio, furniture=not args.no_furniture,
                               shadows=args.shadows)
        if all(f.exists() for f in files):
            skipped += 1
        else:
            write_sample(out, fmt, name, sample, args.area)
        if want_sheet:
            sheet.append(sample)
    if sheet:
        write_contact_sheet(out / "contact_sheet.png", sheet)
    print(f"wrote {args.n - skipped} samples ({skipped} already there) to {out} in format {fmt!r}"
          + (f"; contact sheet {out / 'contact_sheet.png'}" if sheet else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
