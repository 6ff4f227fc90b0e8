"""Writer CLI: ``python -m omnidl.apps.synth --camera noncentral_pano --n 100 --out datasets/synth_nc``.

Renders ``n`` procedural rooms and writes them in a real dataset's on-disk format (see
:mod:`omnidl.synth.export`), resumable (finished samples are skipped), with atomic writes, a progress
bar and a contact sheet PNG (RGB | depth | semantics | layout wireframe) of the first samples.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from tqdm import tqdm

from omnidl.cameras import resolve_camera
from omnidl.synth import SPLITS, render_sample
from omnidl.synth.export import FORMATS, expected_files, sample_name, write_contact_sheet, write_sample


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
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.n < 0:
        raise SystemExit("--n must be >= 0")
    fields = {}
    if args.rc is not None:
        fields["rc"] = args.rc
    cam = resolve_camera(args.camera, args.width, args.height, **fields)
    fmt = args.format or ("stanford" if getattr(cam, "central", True) else "noncentral")
    if fmt in ("noncentral", "horizonnet") and args.rotation != "upright":
        raise SystemExit(f"--format {fmt} needs --rotation upright (the dataset's panoramas are gravity-aligned)")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rc = float(getattr(cam, "rc", getattr(getattr(cam, "base", None), "rc", 0.0)) or 0.0)
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
