"""Convert the official FreDSNet checkpoint (Sbrunoberenguel/FreDSNet, ``FDS``) into omnidl's :class:`FreDSNet`.

The official file is ``{"args": ..., "kargs": {"num_classes", "backbone"}, "state_dict": ...}``. Its
key layout (module names of the public ``FDS`` model) is described by :func:`official_state_dict_shapes`.
The conversion renames keys, drops the entries omnidl does not create (duplicate views of shared
PReLU modules, never-used PReLU/BN parameters, the unused first branch weights ``alphas.0``) and
stacks the branch weights. Load the result into
``FreDSNet(num_classes=..., backbone=..., width=1, semantic_bn_relu=True)`` with ``strict=True``
(:func:`load_official_checkpoint` does all of it).

Outputs of a converted model are close to, not identical with, the official model's: omnidl's
W-convs wrap only horizontally (the official code also wraps top↔bottom) and its spectral skip
is not detached (this changes gradients, not the forward pass).

Command line::

    python -m omnidl.apps.convert_fredsnet FreDSNet_weights.pth fredsnet_omnidl.pth [--overwrite]

The output never replaces the input and replaces an existing file only with ``--overwrite``
(:mod:`omnidl.utils.outputs`); it is written atomically and holds only tensors, numbers, strings and
containers (the official ``args`` as a dict), so it loads with ``torch.load(weights_only=True)``.
"""
from __future__ import annotations

import argparse
import re
from collections import OrderedDict
from typing import Any, Mapping

import torch
from torch import Tensor

from omnidl.models._backbone import build_resnet

FEATURES = (256, 512, 1024, 2048)
LATENT = 1024
DECODER = (2048, 1024, 512, 256, 64, 16)
SEG_MAPS = (1024, 512, 256, 64, 16)
DEPTH_MAPS = (256, 64, 16)
INTER = 128


def _bn(prefix: str, c: int, out: dict) -> None:
    for k in ("weight", "bias", "running_mean", "running_var"):
        out[f"{prefix}.{k}"] = (c,)
    out[f"{prefix}.num_batches_tracked"] = ()


def _circ_conv(prefix: str, cin: int, cout: int, k: int, out: dict) -> None:
    """``CircConv``: children ``Conv``, ``prelu``, ``relu``, ``sigmoid``, ``bn`` (all created)."""
    out[f"{prefix}.Conv.weight"] = (cout, cin, k, k)
    out[f"{prefix}.Conv.bias"] = (cout,)
    out[f"{prefix}.prelu.weight"] = (cout,)
    _bn(f"{prefix}.bn", cout, out)


def _wconv(prefix: str, cin: int, cout: int, out: dict) -> None:
    """``WConv``: ``layer1`` = Sequential(CircConv 1x1, Dropout, CircConv 3x3, Dropout, CircConv 1x1)."""
    h = cin // 4
    _circ_conv(f"{prefix}.layer1.0", cin, h, 1, out)
    _circ_conv(f"{prefix}.layer1.2", h, h, 3, out)
    _circ_conv(f"{prefix}.layer1.4", h, cout, 1, out)


def _fourier_block(prefix: str, c: int, out: dict) -> None:
    """``FourierBlock(1, c)`` → ``block.0`` = ``FastFC(c)`` (children AF1, AF2, conv_ll, conv_lg, conv_gl,
    conv_gg, bnaf1, bnaf2; the PReLUs AF1/AF2 are also bnaf*.1, so they appear twice)."""
    p = f"{prefix}.block.0"
    h = c // 2
    out[f"{p}.AF1.weight"] = (h,)
    out[f"{p}.AF2.weight"] = (h,)
    for name in ("conv_ll", "conv_lg", "conv_gl"):
        out[f"{p}.{name}.weight"] = (h, h, 3, 3)
        out[f"{p}.{name}.bias"] = (h,)
    s, q = f"{p}.conv_gg", h // 2                                       # Spectra(h): inter = h // 2
    out[f"{s}.AF1.weight"] = (q,)
    out[f"{s}.AF2.weight"] = (q,)
    out[f"{s}.inConv.0.weight"] = (q, h, 1, 1)
    out[f"{s}.inConv.0.bias"] = (q,)
    _bn(f"{s}.inConv.1", q, out)
    out[f"{s}.inConv.2.weight"] = (q,)
    out[f"{s}.midConv.0.weight"] = (q, q, 1, 1)
    out[f"{s}.midConv.0.bias"] = (q,)
    _bn(f"{s}.midConv.1", q, out)
    out[f"{s}.midConv.2.weight"] = (q,)
    out[f"{s}.outConv.weight"] = (h, q, 1, 1)
    out[f"{s}.outConv.bias"] = (h,)
    _bn(f"{p}.bnaf1.0", h, out)
    out[f"{p}.bnaf1.1.weight"] = (h,)
    _bn(f"{p}.bnaf2.0", h, out)
    out[f"{p}.bnaf2.1.weight"] = (h,)


def official_state_dict_shapes(num_classes: int = 14, backbone: str = "resnet50") -> "OrderedDict[str, tuple[int, ...]]":
    """Key → shape of the official ``FDS(num_classes, backbone).state_dict()`` (public model definition).

    Only bottleneck ResNets fit the official hard-coded widths (256 ... 2048).
    """
    out: OrderedDict[str, tuple[int, ...]] = OrderedDict()
    for k, v in build_resnet(backbone).state_dict().items():
        out[f"feature_extractor.encoder.{k}"] = tuple(v.shape)
    f = FEATURES
    for i in range(4):
        _fourier_block(f"Encoder.FB{i + 1}", f[i], out)
        _wconv(f"Encoder.convB{i + 1}", f[i], f[i + 1] if i < 3 else LATENT, out)
    d = DECODER
    ins = {4: LATENT, 3: d[0], 2: d[1], 1: d[2]}
    for n, i in zip((4, 3, 2, 1), range(4)):
        _wconv(f"Decoder.convB{n}", ins[n], d[i], out)
        out[f"Decoder.alpha{n}"] = (1,)
        _fourier_block(f"Decoder.FB{n}", d[i], out)
    _wconv("Decoder.U1.0", d[3], d[4], out)
    _fourier_block("Decoder.U1.2", d[4], out)
    _wconv("Decoder.U2.0", d[4], d[5], out)
    _fourier_block("Decoder.U2.2", d[5], out)
    for name, maps, head_out, out_bn in (("SemanticSegmentator", SEG_MAPS, num_classes, True),
                                         ("DepthEstimator", DEPTH_MAPS, 1, False)):
        for i in range(len(maps)):
            out[f"{name}.alphas.{i}"] = (1,)
        for i, c in enumerate(maps):
            _wconv(f"{name}.ScaleMediator.{i}.0", c, INTER, out)
        _circ_conv(f"{name}.out{'Semantic' if out_bn else 'Depth'}Conv", INTER, head_out, 3, out)
    return out


# --- key renaming ---------------------------------------------------------------------------------
_FB = [  # FastFC child -> omnidl FourierBlock child
    (r"conv_ll\.", "ffc.conv_l2l."), (r"conv_lg\.", "ffc.conv_l2g."), (r"conv_gl\.", "ffc.conv_g2l."),
    (r"conv_gg\.inConv\.", "ffc.conv_g2g.conv_in."), (r"conv_gg\.midConv\.0\.", "ffc.conv_g2g.fourier.conv."),
    (r"conv_gg\.midConv\.1\.", "ffc.conv_g2g.fourier.norm."), (r"conv_gg\.midConv\.2\.", "ffc.conv_g2g.fourier.act."),
    (r"conv_gg\.outConv\.", "ffc.conv_g2g.conv_out."), (r"bnaf1\.0\.", "norm_l."), (r"bnaf1\.1\.", "act_l."),
    (r"bnaf2\.0\.", "norm_g."), (r"bnaf2\.1\.", "act_g."),
]
_WC = {"0": "reduce", "2": "conv", "4": "expand"}
_CC = {"Conv": "conv", "bn": "norm", "prelu": "act"}


def _fb_key(rest: str) -> str | None:
    rest = rest[len("block.0."):]
    if re.match(r"(conv_gg\.)?AF[12]\.", rest):
        return None                                     # duplicate view of a shared PReLU
    for pat, rep in _FB:
        if re.match(pat, rest):
            return re.sub("^" + pat, rep, rest)
    raise KeyError(f"unexpected Fourier block key {rest!r}")


def _wc_key(rest: str, relu: bool) -> str | None:
    m = re.match(r"layer1\.([024])\.(Conv|bn|prelu)\.(.+)$", rest)
    if not m:
        raise KeyError(f"unexpected W-conv key {rest!r}")
    if relu and m.group(2) == "prelu":
        return None                                     # never used (ReLU W-convs of the semantic branch)
    return f"{_WC[m.group(1)]}.{_CC[m.group(2)]}.{m.group(3)}"


def convert_key(key: str) -> str | None:
    """omnidl key for an official key, or ``None`` for entries omnidl does not keep (see module docstring)."""
    if key.startswith("feature_extractor.encoder."):
        return "backbone.body." + key[len("feature_extractor.encoder."):]
    m = re.match(r"Encoder\.(FB|convB)(\d)\.(.+)$", key)
    if m:
        i = int(m.group(2)) - 1
        if m.group(1) == "FB":
            sub = _fb_key(m.group(3))
            return f"encoder.{i}.fourier.{sub}" if sub else None
        return f"encoder.{i}.conv.{_wc_key(m.group(3), False)}"
    m = re.match(r"Decoder\.(FB|convB|alpha)(\d)(?:\.(.+))?$", key)
    if m:
        i = 4 - int(m.group(2))
        if m.group(1) == "alpha":
            return f"decoder.{i}.skip_weight"
        if m.group(1) == "FB":
            sub = _fb_key(m.group(3))
            return f"decoder.{i}.fourier.{sub}" if sub else None
        return f"decoder.{i}.conv.{_wc_key(m.group(3), False)}"
    m = re.match(r"Decoder\.U([12])\.([02])\.(.+)$", key)
    if m:
        i = 3 + int(m.group(1))
        if m.group(2) == "0":
            return f"decoder.{i}.conv.{_wc_key(m.group(3), False)}"
        sub = _fb_key(m.group(3))
        return f"decoder.{i}.fourier.{sub}" if sub else None
    m = re.match(r"(SemanticSegmentator|DepthEstimator)\.(.+)$", key)
    if m:
        sem = m.group(1) == "SemanticSegmentator"
        head, rest = ("semantic_head" if sem else "depth_head"), m.group(2)
        if rest.startswith("alphas."):
            return None                                 # stacked separately (see convert_state_dict)
        mm = re.match(r"ScaleMediator\.(\d+)\.0\.(.+)$", rest)
        if mm:
            sub = _wc_key(mm.group(2), relu=sem)
            return f"{head}.mediators.{mm.group(1)}.{sub}" if sub else None
        mm = re.match(r"out(?:Semantic|Depth)Conv\.(Conv|bn|prelu)\.(.+)$", rest)
        if mm:
            if mm.group(1) == "prelu" or (not sem and mm.group(1) == "bn"):
                return None                             # ReLU output: PReLU unused; depth output has no BN
            return f"{head}.out.{_CC[mm.group(1)]}.{mm.group(2)}"
    raise KeyError(f"unexpected key {key!r} in the official FreDSNet state dict")


def convert_state_dict(official: Mapping[str, Tensor]) -> "OrderedDict[str, Tensor]":
    """Rename an official ``FDS`` state dict to omnidl's :class:`FreDSNet` (``width=1``, ``semantic_bn_relu=True``)."""
    out: OrderedDict[str, Tensor] = OrderedDict()
    for k, v in official.items():
        new = convert_key(k)
        if new is not None:
            out[new] = v
    for name, head in (("SemanticSegmentator", "semantic_head"), ("DepthEstimator", "depth_head")):
        idx = sorted(int(k.rsplit(".", 1)[1]) for k in official if k.startswith(f"{name}.alphas."))
        if idx:
            out[f"{head}.branch_weights"] = torch.cat([official[f"{name}.alphas.{i}"].reshape(1) for i in idx[1:]])
    return out


def load_official_checkpoint(path: str, map_location: str | torch.device = "cpu", weights_only: bool = True,
                             **model_kwargs: Any):
    """Build omnidl's FreDSNet from an official checkpoint file (``{'kargs', 'state_dict', ...}`` or a bare
    state dict) and load the converted weights with ``strict=True``. Returns ``(model, checkpoint_args)``.

    The file is read with ``torch.load(weights_only=True)`` (tensors, numbers, strings, containers and the
    ``argparse.Namespace`` of the official ``args``: nothing that can run code). ``weights_only=False``
    (``--unsafe-pickle``) un-pickles arbitrary objects: an explicit opt-out, only for files you trust that hold
    other Python objects.
    """
    from omnidl.models.fredsnet import FreDSNet
    try:   # argparse.Namespace (the official file's "args") is allowed: unpickling it only sets attributes
        with torch.serialization.safe_globals([argparse.Namespace]):
            ckpt = torch.load(path, map_location=map_location, weights_only=weights_only)
    except FileNotFoundError:
        raise FileNotFoundError(f"official FreDSNet checkpoint {path!r} not found (download it yourself from "
                                "the link in the FreDSNet README)") from None
    except Exception as exc:  # noqa: BLE001  (torch raises UnpicklingError subclasses)
        if not weights_only:
            raise
        raise ValueError(f"{path!r} could not be read with torch.load(weights_only=True) ({exc}); if you trust "
                         "the file, pass weights_only=False (--unsafe-pickle on the command line)") from exc
    sd = ckpt.get("state_dict", ckpt) if isinstance(ckpt, dict) else None
    if not isinstance(sd, Mapping):
        raise ValueError(f"{path!r}: expected a FreDSNet checkpoint dict with a 'state_dict', got {type(ckpt).__name__}")
    kargs = dict(ckpt.get("kargs", {})) if "state_dict" in ckpt else {}
    kwargs = dict(num_classes=int(kargs.get("num_classes", 14)), backbone=kargs.get("backbone", "resnet50"),
                  width=1.0, semantic_bn_relu=True)
    kwargs.update(model_kwargs)
    if not sd:
        raise ValueError(f"{path!r}: the state dict is empty; expected the official FreDSNet weights")
    try:
        converted = convert_state_dict(sd)
    except KeyError as exc:
        raise ValueError(f"{path!r} does not look like the official FreDSNet checkpoint: {exc.args[0]}") from None
    model = FreDSNet(**kwargs)
    try:
        model.load_state_dict(converted, strict=True)
    except RuntimeError as exc:
        raise ValueError(f"{path!r}: the converted weights do not fit FreDSNet({kwargs}): {str(exc)[:600]}") from None
    args = ckpt.get("args") if "state_dict" in ckpt else None
    return model, (vars(args) if isinstance(args, argparse.Namespace) else args)


def main(argv: list[str] | None = None) -> int:
    import sys
    from pathlib import Path

    from omnidl.utils.io import atomic_torch_save
    ap = argparse.ArgumentParser(prog="python -m omnidl.apps.convert_fredsnet", description=__doc__.split("\n\n")[0])
    ap.add_argument("official", help="official FreDSNet checkpoint (.pth)")
    ap.add_argument("output", help="where to write {'model_kwargs', 'state_dict'} for omnidl")
    ap.add_argument("--unsafe-pickle", action="store_true", help="torch.load(weights_only=False): trusted files only")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing output file (never the input)")
    a = ap.parse_args(argv)
    from omnidl.utils.outputs import OutputIsInputError, guard_outputs
    if Path(a.output).is_dir():
        print(f"error: the output {a.output} is a folder; give a file path (e.g. fredsnet_omnidl.pth)", file=sys.stderr)
        return 2
    try:   # the output policy (omnidl.utils.outputs): never the input, an existing file only with --overwrite
        guard_outputs([a.output], [a.official], overwrite=a.overwrite, option="--overwrite")
    except OutputIsInputError:
        print(f"error: the output {a.output} is the official checkpoint itself; give another path", file=sys.stderr)
        return 2
    except FileExistsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        model, args = load_official_checkpoint(a.official, weights_only=not a.unsafe_pickle)
    except (FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    kwargs = dict(num_classes=model.num_classes, backbone=model.backbone.name, width=1.0, semantic_bn_relu=True)
    atomic_torch_save(a.output, {"model_kwargs": kwargs, "state_dict": model.state_dict(), "official_args": args})
    print(f"wrote {a.output}: build with create_model('fredsnet', **{kwargs})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
