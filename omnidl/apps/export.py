"""``omnidl export CKPT OUT [--format pt2|onnx]``: a checkpoint's network as a file other runtimes load.

* ``pt2`` (default for ``*.pt2``): a ``torch.export`` program (``torch.export.save``; load it with
  ``torch.export.load(OUT).module()``), projected convolutions included (they export as the registered ops
  ``omnidl::projected_sampling``/``omnidl::fixed_offset_conv2d``, so loading needs ``import omnidl``);
* ``onnx`` (default for ``*.onnx``): ONNX opset 18 through the dynamo exporter (``pip install
  "omnidl[export]"``). ONNX has no projected-convolution operator: such a model is refused with that said.

CKPT is anything ``omnidl predict`` loads (:func:`omnidl.apps.predict.loader.load_predictor`): a ``train.py``
checkpoint, converted FreDSNet weights, an official HorizonNet ``.pth``. The network takes ``(1, 3, H, W)``
images in [0, 1] at the checkpoint's input size (printed) and returns its named outputs. After writing, the
exported program runs on a random input and must match eager PyTorch within ``--atol`` (else an error and no
file). OUT is never overwritten without ``--overwrite``, never the checkpoint itself, and written atomically.
"""
from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

import torch

FORMATS = ("pt2", "onnx")


def _format_of(out: Path, given: str | None) -> str:
    if given:
        return given
    suffix = out.suffix.lower().lstrip(".")
    if suffix in FORMATS:
        return suffix
    raise ValueError(f"OUT {str(out)!r}: cannot tell the format from the suffix {out.suffix!r}; name it *.pt2 or "
                     f"*.onnx or pass --format {'|'.join(FORMATS)}")


def _max_diff(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> float:
    if set(a) != set(b):
        raise RuntimeError(f"the exported program returns {sorted(b)}, the model {sorted(a)}")
    return max((float((a[k].float() - b[k].float()).abs().max()) for k in a), default=0.0)


def export_pt2(model: torch.nn.Module, x: torch.Tensor, out: Path, atol: float) -> float:
    """``torch.export`` ``model`` at ``x``'s shape into ``out`` (atomic); returns the reloaded program's largest
    difference from eager on ``x``."""
    from omnidl.utils.io import atomic_write
    with torch.no_grad():
        ref = model(x)
        ep = torch.export.export(model, (x,))
    atomic_write(out, lambda tmp: torch.export.save(ep, tmp))
    with torch.no_grad():
        got = torch.export.load(str(out)).module()(x)
    return _max_diff(ref, got)


def export_onnx(model: torch.nn.Module, x: torch.Tensor, out: Path, atol: float) -> float:
    """ONNX (dynamo exporter, one file) of ``model`` at ``x``'s shape into ``out`` (atomic); returns
    onnxruntime's largest difference from eager on ``x`` (``nan`` when onnxruntime is not installed)."""
    from omnidl.utils.io import atomic_write
    with torch.no_grad():
        ref = model(x)
    names = list(ref)
    atomic_write(out, lambda tmp: torch.onnx.export(model, (x,), tmp, dynamo=True, output_names=names,
                                                    external_data=False, verbose=False))
    try:
        import onnxruntime as ort
    except ImportError:
        return float("nan")
    sess = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    outs = sess.run(None, {sess.get_inputs()[0].name: x.numpy()})
    got = {o.name: torch.from_numpy(v) for o, v in zip(sess.get_outputs(), outs)}
    return _max_diff(ref, got)


def _uses_projected_conv(model: torch.nn.Module) -> bool:
    return any(type(m).__name__ == "ProjectedConv2d" for m in model.modules())


def run(checkpoint: str | os.PathLike, out: str | os.PathLike, fmt: str | None = None, overwrite: bool = False,
        atol: float = 1e-4, seed: int = 0) -> dict:
    """Export ``checkpoint`` to ``out``; returns ``{"format", "out", "model", "input": [1, 3, H, W], "outputs",
    "max_abs_diff"}``. Errors (``FileExistsError``, ``ValueError``, ``RuntimeError``) name the file."""
    ckpt, out = Path(checkpoint), Path(out)
    fmt = _format_of(out, fmt)
    if out.exists() and ckpt.exists() and out.resolve() == ckpt.resolve():
        raise ValueError(f"OUT {str(out)!r} is the checkpoint itself: choose another file name")
    if out.exists() and not overwrite:
        raise FileExistsError(f"OUT {str(out)!r} exists: pass --overwrite to replace it, or choose another name")
    if out.is_dir():
        raise IsADirectoryError(f"OUT {str(out)!r} is a folder: give a file name (*.{fmt})")
    from .predict.loader import load_predictor
    pred = load_predictor(ckpt, "cpu")
    model = pred.model.float().eval()
    if fmt == "onnx":
        if _uses_projected_conv(model):
            raise ValueError(f"{ckpt}: the {pred.name} network uses projected convolutions (model.conv=projected), "
                             "which ONNX has no operator for; export it as pt2 (torch.export) instead")
        try:
            import onnxscript  # noqa: F401 (torch.onnx's dynamo exporter needs it)
        except ImportError:
            raise RuntimeError('ONNX export needs the onnx and onnxscript packages: pip install "omnidl[export]"') \
                from None
    x = torch.rand(1, 3, pred.height, pred.width, generator=torch.Generator().manual_seed(seed))
    try:
        diff = (export_pt2 if fmt == "pt2" else export_onnx)(model, x, out, atol)
    except (RuntimeError, ValueError, TypeError, NotImplementedError) as e:
        raise RuntimeError(f"{ckpt}: exporting {pred.name} to {fmt} failed ({type(e).__name__}: {e})") from e
    if diff > atol:  # nan (no onnxruntime to check with) passes
        out.unlink(missing_ok=True)
        raise RuntimeError(f"{ckpt}: the exported {fmt} program differs from PyTorch by {diff:.3g} (> --atol "
                           f"{atol:g}) on a random input; nothing written")
    return {"format": fmt, "out": str(out), "model": pred.name, "input": [1, 3, pred.height, pred.width],
            "outputs": sorted(pred.outputs), "max_abs_diff": diff}


def build_parser(prog: str = "omnidl export") -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoint", help="best.pt/last.pt of train.py, converted FreDSNet weights or a HorizonNet .pth")
    ap.add_argument("out", help="the file to write (*.pt2 or *.onnx)")
    ap.add_argument("--format", choices=FORMATS, default=None, help="default: from OUT's suffix")
    ap.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    ap.add_argument("--atol", type=float, default=1e-4, help="largest accepted difference from eager PyTorch")
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        info = run(args.checkpoint, args.out, args.format, args.overwrite, args.atol)
    except (FileNotFoundError, FileExistsError, IsADirectoryError, ValueError, RuntimeError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    n, c, h, w = info["input"]
    check = "not checked (no onnxruntime)" if info["max_abs_diff"] != info["max_abs_diff"] else \
        f"max |exported - eager| = {info['max_abs_diff']:.2e}"
    print(f"{info['model']} -> {info['out']} ({info['format']}): input ({n}, {c}, {h}, {w}) RGB in [0, 1], "
          f"outputs {info['outputs']}; {check}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
