"""Evaluate a checkpoint: ``python evaluate.py model=fredsnet checkpoint=PATH [data=folder data.root=DIR]``
(see docs/engine.md).

A thin wrapper of ``omnidl evaluate`` (:mod:`omnidl.apps.evaluate`), kept for the README's commands: writes
metrics, per-image records, pictures and point clouds (:mod:`omnidl.engine.evaluator`), then the static page
``report.html`` over them (:mod:`omnidl.apps.html_report`)."""
import sys

from omnidl.apps.evaluate import main

if __name__ == "__main__":
    sys.exit(main())
