"""The ``omnidl`` console script (``[project.scripts]``): one command per application::

    omnidl train model=fredsnet [key=value ...]            # Hydra app, = python train.py ...
    omnidl evaluate model=fredsnet checkpoint=PATH [...]   # Hydra app, = python evaluate.py ...
    omnidl predict depth|layout|upright|stabilise INPUT [--checkpoint CKPT] --out DIR
    omnidl export CKPT OUT [--format pt2|onnx]
    omnidl synth --camera NAME --n N --out DIR
    omnidl reproject --src IMG --dst-camera CAM --out IMG
    omnidl calib convert IN OUT --to FORMAT | omnidl calib show FILE [--out PNG]
    omnidl report SWEEP_DIR [--out DIR]

``omnidl COMMAND -h`` gives each command's options; ``python -m omnidl.apps.cli ...`` is the same without the
installed script. The configs and camera presets come from the installed package (``omnidl/configs``), so every
command works outside a source checkout.
"""
from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from importlib import import_module

#: command -> (module of omnidl.apps with a ``main(argv)``, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "train": ("omnidl.apps.train", "train a model (Hydra: model=NAME key=value ...; omnidl train --help)"),
    "evaluate": ("omnidl.apps.evaluate", "evaluate a checkpoint: metrics, pictures, point clouds, report.html "
                                         "(Hydra: model=NAME checkpoint=PATH ...)"),
    "predict": ("omnidl.apps.predict", "run a trained model (or the weight-free upright estimator) on an "
                                       "image, a folder or a video"),
    "export": ("omnidl.apps.export", "write a checkpoint's network as a torch.export program (.pt2) or ONNX"),
    "synth": ("omnidl.apps.synth", "render procedural rooms into a dataset format"),
    "reproject": ("omnidl.apps.reproject", "render another camera's image from an image (a panorama by default)"),
    "calib": ("omnidl.apps.calib", "calibration files: convert between formats, show a camera (FOV, validity, "
                                   "image circle)"),
    "report": ("omnidl.apps.report", "collect a sweep's metrics into results.md/results.csv"),
}
#: Hydra apps read ``sys.argv`` themselves; the others take ``argv``
HYDRA_APPS = ("train", "evaluate")


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = [f"  {name:<{width}}  {text}" for name, (_, text) in COMMANDS.items()]
    return ("usage: omnidl COMMAND [options]   (omnidl COMMAND -h for a command's options)\n\ncommands:\n"
            + "\n".join(lines) + "\n")


def _entry(command: str) -> Callable[..., int | None]:
    return import_module(COMMANDS[command][0]).main


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0 if argv else 2
    cmd, rest = argv[0], argv[1:]
    if cmd not in COMMANDS:
        print(f"omnidl: unknown command {cmd!r}\n{usage()}", file=sys.stderr)
        return 2
    run = _entry(cmd)
    if cmd in HYDRA_APPS:
        return int(run(rest, prog=f"omnidl {cmd}") or 0)
    if cmd == "predict":
        return int(run(rest, prog="omnidl predict") or 0)
    return int(run(rest) or 0)


if __name__ == "__main__":
    sys.exit(main())
