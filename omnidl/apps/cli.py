"""The ``omnidl`` console script (``[project.scripts]``)::

    omnidl predict depth|layout|upright|stabilise INPUT --checkpoint CKPT --out DIR

``python -m omnidl.apps.cli ...`` is the same without the installed script.
"""
from __future__ import annotations

import sys
from collections.abc import Sequence

USAGE = """usage: omnidl predict depth|layout|upright|stabilise INPUT [--checkpoint CKPT] --out DIR [options]

commands:
  predict    run a trained model (or the weight-free upright estimator) on an image, a folder or a video
             (omnidl predict -h for the options)
"""


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE)
        return 0 if argv else 2
    cmd, rest = argv[0], argv[1:]
    if cmd == "predict":
        from omnidl.apps.predict import main as predict_main
        return predict_main(rest)
    print(f"omnidl: unknown command {cmd!r}\n{USAGE}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
