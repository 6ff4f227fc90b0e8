"""``python -m omnidl.apps.html_report RUN_DIR [--overwrite]``: (re)build ``RUN_DIR/report.html`` from an
evaluation run folder (an existing report is replaced only with ``--overwrite``)."""
from __future__ import annotations

import argparse
import sys

from . import write_report


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m omnidl.apps.html_report", description=__doc__)
    ap.add_argument("run_dir", help="the run folder of `python evaluate.py ...` (holds metrics.json)")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing report.html (and its assets)")
    args = ap.parse_args(argv)
    try:
        path = write_report(args.run_dir, overwrite=args.overwrite)
    except (FileNotFoundError, FileExistsError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {path} (open it in a browser)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
