"""Robustness table: every loss (depth, segmentation, heat map, layout, joint) on bad numeric inputs (issue 14).

Policy (see the loss docstrings): NaN/inf in a *masked* target (depth, boundary angles) marks those pixels invalid
and is counted in a flag term; NaN/inf or out-of-range values in a *dense* target (labels, heat maps, corner heat)
are a clear error naming the key, the value and the samples; NaN/inf in *predictions* propagate to a non-finite
loss, which the engine's ``trainer.skip_nonfinite`` guard skips (a loss must not hide a diverged model).
An empty batch gives a zero loss with a ``no_valid_*`` flag; a zero-size map (H or W = 0) is an error.
"""
from __future__ import annotations

import re
import warnings

import pytest
import torch

from omnidl.losses.depth import DepthLoss, adaptive_berhu_loss, depth_loss, margin_loss
from omnidl.losses.heatmap import HeatmapLoss
from omnidl.losses.joint import JointLoss, object_loss
from omnidl.losses.layout import LayoutLoss
from omnidl.losses.segmentation import SegmentationLoss, recall_loss, weighted_cross_entropy

from .verdicts import ERROR, OK, expect, row

B, C, H, W = 2, 14, 8, 16
META = [{"name": "roomA_pano1", "image": "data/roomA/pano1.png"},
        {"name": "roomB_pano7", "image": "data/roomB/pano7.png"}]


def _g(seed=0):
    return torch.Generator().manual_seed(seed)


def depth_pair(b=B, h=H, w=W, scale=1.0):
    pred = torch.rand(b, 1, h, w, generator=_g(1)) * 4 + 0.5
    target = (torch.rand(b, 1, h, w, generator=_g(2)) * 4 + 0.5) * scale
    return pred, target


def depth_call(pred, target, loss=None, meta=True):
    batch = {"depth": target}
    if meta:
        batch["meta"] = META[:target.shape[0]]
    loss = loss or DepthLoss(alpha_margin=0.001)
    return lambda: loss({"depth": pred}, batch)


def with_px(t, value, where=(0, 0, 2, 3)):
    t = t.clone()
    t[where] = value
    return t


def seg_inputs(b=B, h=H, w=W, c=C):
    logits = torch.randn(b, c, h, w, generator=_g(3))
    labels = torch.randint(1, c, (b, h, w), generator=_g(4))
    return logits, labels


def seg_call(logits, labels, loss=None, meta=True):
    batch = {"semantic": labels}
    if meta:
        batch["meta"] = META[:labels.shape[0]]
    loss = loss or SegmentationLoss()
    return lambda: loss({"semantic": logits}, batch)


def heat_inputs(b=B, h=H, w=W, ph=None, pw=None):
    ph, pw = ph or h // 2, pw or w // 2
    outputs = {"horizon": torch.randn(b, 1, ph, pw, generator=_g(5)), "vp": torch.randn(b, 1, ph, pw, generator=_g(6)),
               "aux_0": torch.randn(b, 2, max(ph // 2, 1), max(pw // 2, 1), generator=_g(7))}
    batch = {"horizon_map": torch.rand(b, 1, h, w, generator=_g(8)), "vp_map": torch.rand(b, 1, h, w, generator=_g(9)),
             "meta": META[:b]}
    return outputs, batch


def heat_call(outputs, batch, loss=None):
    loss = loss or HeatmapLoss()
    return lambda: loss(outputs, batch)


def layout_inputs(b=B, h=32, w=W):
    outputs = {"boundary": torch.randn(b, 2, w, generator=_g(10)) * 0.3,
               "corner": torch.randn(b, 1, w, generator=_g(11))}
    rows = torch.stack([torch.full((b, w), h * 0.3), torch.full((b, w), h * 0.7)], 1)
    batch = {"image": torch.zeros(b, 3, h, w), "boundary": rows, "corner_heat": torch.rand(b, 1, w, generator=_g(12)),
             "meta": META[:b]}
    return outputs, batch


def layout_call(outputs, batch, loss=None):
    loss = loss or LayoutLoss()
    return lambda: loss(outputs, batch)


def joint_inputs(b=B, h=H, w=W, scale=1.0):
    pred, target = depth_pair(b, h, w, scale)
    logits, labels = seg_inputs(b, h, w)
    return {"depth": pred, "semantic": logits}, {"depth": target, "semantic": labels, "meta": META[:b]}


def joint_call(outputs, batch, loss=None):
    loss = loss or JointLoss()
    return lambda: loss(outputs, batch)


def _set(d, **kw):
    return {**d, **kw}


def edited(inputs, call, out=None, batch=None):
    """``call(outputs, batch)`` on ``inputs = (outputs, batch)`` after applying the edits ``out`` / ``batch``."""
    o, b = inputs
    return call(out(o) if out else o, batch(b) if batch else b)


NAN = float("nan")


# ---------------------------------------------------------------------------------------------- checks of OK rows
def finite(out, caught):
    loss = out[0] if isinstance(out, tuple) else out
    assert torch.isfinite(loss).all(), f"loss {loss} is not finite"


def finite_no_warning(out, caught):
    finite(out, caught)
    assert not caught, f"unexpected warnings {[str(w.message) for w in caught]}"


def nonfinite_loss(out, caught):
    loss = out[0] if isinstance(out, tuple) else out
    assert not torch.isfinite(loss).all(), "a diverged prediction must give a non-finite loss (the engine skips it)"


def flag(*names, zero=False, warn=None):
    def check(out, caught):
        loss, terms = out
        assert torch.isfinite(loss), f"loss {loss} is not finite"
        for n in names:
            assert terms.get(n, 0) > 0, f"flag {n!r} missing from {terms}"
        if zero:
            assert float(loss) == 0.0
        if warn:
            msgs = [str(w.message) for w in caught]
            assert any(re.search(warn, m, re.I) for m in msgs), f"no warning matching {warn!r} in {msgs}"
    return check


def warns_once(pattern):
    """The unit warning: given on the first call of a loss instance, not repeated on the second."""
    def check(out, caught):
        (loss, _terms), second = out
        assert torch.isfinite(loss)
        msgs = [str(w.message) for w in caught]
        assert sum(bool(re.search(pattern, m, re.I)) for m in msgs) == 1, \
            f"expected one warning matching {pattern!r}, got {msgs}"
    return check


def twice(make):
    def fn():
        f = make()
        return f(), f()
    return fn


def same_as(reference):
    def check(out, caught):
        finite(out, caught)
        ref = reference()
        a = out[0] if isinstance(out, tuple) else out
        b = ref[0] if isinstance(ref, tuple) else ref
        torch.testing.assert_close(a, b)
    return check


def nan_depth_equals_zero_depth(out, caught):
    """NaN target pixels count as invalid: same loss as with those pixels at 0 (invalid), flagged."""
    loss, terms = out
    pred, target = depth_pair()
    ref, _ = DepthLoss(alpha_margin=0.001)({"depth": pred}, {"depth": with_px(target, 0.0)})
    torch.testing.assert_close(loss, ref)
    assert terms.get("nonfinite_depth") == 1.0, terms


def last_class_weighted(out, caught):
    """``ignore_index=-1`` must not silently zero the weight of the last class (``w[-1]``)."""
    assert out[-1] > 0 and out[0] > 0, out


_P, _T = depth_pair()
_L, _Y = seg_inputs()


def _labels_with(value, sample=1):
    y = _Y.clone()
    y[sample, 3, 4] = value
    return y


ROWS = [
    # ------------------------------------------------------------------------------------------------ depth
    row("depth-nan-target-masked-flagged", lambda: depth_call(_P, with_px(_T, NAN)),
        nan_depth_equals_zero_depth, verdict=OK),
    row("depth-inf-target-masked-flagged", lambda: depth_call(_P, with_px(_T, float("inf"))),
        flag("nonfinite_depth"), verdict=OK),
    row("depth-all-nan-target-zero-flagged", lambda: depth_call(_P, torch.full_like(_T, NAN)),
        flag("nonfinite_depth", "no_valid_depth", zero=True, warn="no valid depth"), verdict=OK),
    row("depth-nan-pred-propagates", lambda: depth_call(with_px(_P, NAN), _T), nonfinite_loss, verdict=OK),
    row("depth-inf-pred-propagates", lambda: depth_call(with_px(_P, float("inf")), _T), nonfinite_loss, verdict=OK),
    row("depth-all-invalid-zero-flagged", lambda: depth_call(_P, torch.zeros_like(_T)),
        flag("no_valid_depth", zero=True, warn="no valid depth"), verdict=OK),
    row("depth-negative-target-invalid", lambda: depth_call(_P, -_T), flag("no_valid_depth", zero=True), verdict=OK),
    row("depth-empty-batch-zero-flagged", lambda: depth_call(_P[:0], _T[:0]), flag("no_valid_depth", zero=True),
        verdict=OK),
    row("depth-zero-size-map", lambda: depth_call(_P[..., :0, :], _T[..., :0, :]), None,
        verdict=ERROR, match=r"outputs\['depth'\].*zero-size.*\(2, 1, 0, 16\)"),
    row("depth-shape-mismatch", lambda: depth_call(_P, _T[..., :8]), None,
        verdict=ERROR, match=r"\(2, 1, 8, 16\).*\(2, 1, 8, 8\)"),
    row("depth-channels-mismatch", lambda: depth_call(torch.cat([_P, _P], 1), _T), None,
        verdict=ERROR, match=r"\(2, 2, 8, 16\).*\(2, 1, 8, 16\)"),
    row("depth-fn-broadcast-mismatch", lambda: (lambda: depth_loss(_P, _T[:1])), None,
        verdict=ERROR, match=r"depth_loss.*\(2, 1, 8, 16\).*\(1, 1, 8, 16\)"),
    row("margin-fn-broadcast-mismatch", lambda: (lambda: margin_loss(_P, _T[:1])), None,
        verdict=ERROR, match=r"margin_loss.*\(2, 1, 8, 16\).*\(1, 1, 8, 16\)"),
    row("berhu-fn-explicit-mask-over-nan", lambda: (lambda: adaptive_berhu_loss(
        _P, with_px(_T, NAN), torch.ones_like(_T, dtype=torch.bool))), finite, verdict=OK),
    row("margin-fn-explicit-mask-over-inf", lambda: (lambda: margin_loss(
        _P, with_px(_T, float("inf")), torch.ones_like(_T, dtype=torch.bool))), finite, verdict=OK),
    row("depth-int-target-cast", lambda: depth_call(_P, _T.round().long()),
        same_as(lambda: DepthLoss(alpha_margin=0.001)({"depth": _P}, {"depth": _T.round()})), verdict=OK),
    row("depth-int-prediction", lambda: depth_call(_P.round().long(), _T), None,
        verdict=ERROR, match=r"outputs\['depth'\].*floating.*int64"),
    row("depth-fp16", lambda: depth_call(_P.half(), _T), finite, verdict=OK),
    row("depth-3d-inputs", lambda: depth_call(_P[:, 0], _T[:, 0]), finite, verdict=OK),
    row("depth-odd-1x1", lambda: depth_call(*depth_pair(h=1, w=1)), finite, verdict=OK),
    row("depth-odd-3x5", lambda: depth_call(*depth_pair(h=3, w=5)), finite, verdict=OK),
    row("depth-odd-7x1", lambda: depth_call(*depth_pair(h=7, w=1)), finite, verdict=OK),
    row("depth-millions-of-metres-warns-once", lambda: twice(lambda: depth_call(*depth_pair(scale=1e6))),
        warns_once(r"not in metres.*millimetres"), verdict=OK),
    row("depth-pred-1000x-target-warns-once", lambda: twice(lambda: depth_call(_P * 1000, _T)),
        warns_once(r"scale.*prediction"), verdict=OK),
    row("depth-metres-no-warning", lambda: depth_call(_P, _T), finite_no_warning, verdict=OK),
    row("depth-untrained-small-pred-no-warning", lambda: depth_call(_P * 1e-3, _T), finite_no_warning, verdict=OK),
    # ------------------------------------------------------------------------------------------------ segmentation
    row("seg-label-14-of-14", lambda: seg_call(_L, _labels_with(14)), None,
        verdict=ERROR, match=r"batch\['semantic'\].*\b14\b.*\[0, 14\).*14 classes.*roomB_pano7"),
    row("seg-label-minus-1", lambda: seg_call(_L, _labels_with(-1, sample=0)), None,
        verdict=ERROR, match=r"-1.*\[0, 14\).*roomA_pano1"),
    row("seg-label-255-void", lambda: seg_call(_L, _labels_with(255)), None,
        verdict=ERROR, match=r"255.*ignore index 0"),
    row("seg-label-14-no-meta", lambda: seg_call(_L, _labels_with(14), meta=False), None,
        verdict=ERROR, match=r"\b14\b.*14 classes"),
    row("seg-recall-label-14", lambda: seg_call(_L, _labels_with(14), SegmentationLoss("recall")), None,
        verdict=ERROR, match=r"\b14\b.*14 classes.*roomB_pano7"),
    row("seg-batch-weights-label-14", lambda: seg_call(_L, _labels_with(14), SegmentationLoss(class_weights="batch")),
        None, verdict=ERROR, match=r"\b14\b.*14 classes"),
    row("seg-fn-ce-label-14", lambda: (lambda: weighted_cross_entropy(_L, _labels_with(14))), None,
        verdict=ERROR, match=r"\b14\b.*14 classes"),
    row("seg-fn-recall-label-minus-1", lambda: (lambda: recall_loss(_L, _labels_with(-1))), None,
        verdict=ERROR, match=r"-1.*14 classes"),
    row("seg-all-ignored-zero-flagged", lambda: seg_call(_L, torch.zeros_like(_Y)),
        flag("no_valid_semantic", zero=True, warn="labelled"), verdict=OK),
    row("seg-empty-batch-zero-flagged", lambda: seg_call(_L[:0], _Y[:0]), flag("no_valid_semantic", zero=True),
        verdict=OK),
    row("seg-zero-size-map", lambda: seg_call(_L[..., :0], _Y[..., :0]), None,
        verdict=ERROR, match=r"outputs\['semantic'\].*zero-size"),
    row("seg-float-integral-labels", lambda: seg_call(_L, _Y.float()),
        same_as(lambda: SegmentationLoss()({"semantic": _L}, {"semantic": _Y})), verdict=OK),
    row("seg-float-fractional-labels", lambda: seg_call(_L, _Y.float() + 0.5), None,
        verdict=ERROR, match=r"batch\['semantic'\].*non-integer.*nearest"),
    row("seg-nan-labels", lambda: seg_call(_L, with_px(_Y.float(), NAN, (1, 2, 2))), None,
        verdict=ERROR, match=r"batch\['semantic'\].*(NaN|non-finite).*roomB_pano7"),
    row("seg-uint8-labels", lambda: seg_call(_L, _Y.to(torch.uint8)),
        same_as(lambda: SegmentationLoss()({"semantic": _L}, {"semantic": _Y})), verdict=OK),
    row("seg-void-255-as-ignore-index", lambda: seg_call(_L, _labels_with(255), SegmentationLoss(ignore_index=255)),
        finite, verdict=OK),
    row("seg-recall-void-255-as-ignore-index", lambda: seg_call(_L, _labels_with(255), SegmentationLoss(
        "recall", ignore_index=255)), finite, verdict=OK),
    row("seg-void-255-batch-weights", lambda: seg_call(_L, _labels_with(255), SegmentationLoss(
        class_weights="batch", ignore_index=255)), finite, verdict=OK),
    row("seg-void-255-class-frequencies", lambda: seg_call(_L, _labels_with(255), SegmentationLoss(
        class_frequencies=list(range(1, C + 1)), ignore_index=255)), finite, verdict=OK),
    row("seg-ignore-minus-1-keeps-last-class-weight", lambda: (lambda: SegmentationLoss(
        class_frequencies=list(range(1, C + 1)), ignore_index=-1).weight), last_class_weighted, verdict=OK),
    row("seg-labels-b1hw", lambda: seg_call(_L, _Y[:, None]), finite, verdict=OK),
    row("seg-shape-mismatch", lambda: seg_call(_L, _Y[..., :8]), None,
        verdict=ERROR, match=r"\(2, 14, 8, 16\).*\(2, 8, 8\)"),
    row("seg-int-logits", lambda: seg_call(_L.long(), _Y), None, verdict=ERROR, match=r"floating.*int64"),
    row("seg-nan-logits-propagates", lambda: seg_call(with_px(_L, NAN), _Y), nonfinite_loss, verdict=OK),
    row("seg-odd-1x1", lambda: seg_call(*seg_inputs(h=1, w=1)), finite, verdict=OK),
    row("seg-odd-5x3", lambda: seg_call(*seg_inputs(h=5, w=3)), finite, verdict=OK),
    # ------------------------------------------------------------------------------------------------ heat maps
    row("heat-nan-target", lambda: edited(heat_inputs(), heat_call, batch=lambda b: _set(
        b, horizon_map=with_px(b["horizon_map"], NAN, (1, 0, 1, 1)))),
        None, verdict=ERROR, match=r"batch\['horizon_map'\].*(NaN|non-finite).*roomB_pano7"),
    row("heat-uint8-target-0-255", lambda: edited(heat_inputs(), heat_call, batch=lambda b: _set(
        b, vp_map=(b["vp_map"] * 255).to(torch.uint8))), None,
        verdict=ERROR, match=r"batch\['vp_map'\].*25\d.*\[0, 1\]"),
    row("heat-negative-target", lambda: edited(heat_inputs(), heat_call, batch=lambda b: _set(
        b, vp_map=b["vp_map"] - 2)),
        None, verdict=ERROR, match=r"batch\['vp_map'\].*\[0, 1\]"),
    row("heat-nan-logits-propagates", lambda: edited(heat_inputs(), heat_call, out=lambda o: _set(
        o, horizon=with_px(o["horizon"], NAN))), nonfinite_loss, verdict=OK),
    row("heat-batch-mismatch", lambda: edited(heat_inputs(), heat_call, out=lambda o: _set(o, vp=o["vp"][:1])), None,
        verdict=ERROR, match=r"outputs\['vp'\].*\(1, 1, 4, 8\).*batch\['vp_map'\].*\(2, 1, 8, 16\)"),
    row("heat-empty-batch-zero-flagged", lambda: heat_call(*heat_inputs(b=0)), flag("no_valid_heatmap", zero=True),
        verdict=OK),
    row("heat-zero-size-logits", lambda: edited(heat_inputs(), heat_call, out=lambda o: _set(
        o, horizon=o["horizon"][..., :0])), None, verdict=ERROR, match=r"outputs\['horizon'\].*zero-size"),
    row("heat-odd-sizes", lambda: heat_call(*heat_inputs(h=7, w=13, ph=3, pw=5)), finite, verdict=OK),
    row("heat-upsampled-target", lambda: heat_call(*heat_inputs(h=3, w=5, ph=6, pw=10)), finite, verdict=OK),
    row("heat-bool-targets", lambda: edited(heat_inputs(), heat_call, batch=lambda b: _set(
        b, horizon_map=b["horizon_map"] > 0.5)), finite, verdict=OK),
    row("heat-int-logits", lambda: edited(heat_inputs(), heat_call, out=lambda o: _set(o, vp=o["vp"].long())), None,
        verdict=ERROR, match=r"outputs\['vp'\].*floating"),
    row("heat-missing-target", lambda: edited(heat_inputs(), heat_call,
                                              batch=lambda b: {"horizon_map": b["horizon_map"]}),
        None, verdict=ERROR, match=r"vp_map"),
    # ------------------------------------------------------------------------------------------------ layout
    row("layout-nan-boundary-masked-flagged", lambda: edited(layout_inputs(), layout_call, batch=lambda b: _set(
        b, boundary=with_px(b["boundary"], NAN, (0, 0, 3)))), flag("nonfinite_boundary"), verdict=OK),
    row("layout-all-invalid-boundary", lambda: edited(layout_inputs(), layout_call, batch=lambda b: _set(
        b, boundary_valid=torch.zeros_like(b["boundary"], dtype=torch.bool))),
        flag("no_valid_boundary", warn="no valid boundary"), verdict=OK),
    row("layout-corner-heat-3.9e17", lambda: edited(layout_inputs(), layout_call, batch=lambda b: _set(
        b, corner_heat=with_px(b["corner_heat"], 3.9e17, (1, 0, 5)))), None,
        verdict=ERROR, match=r"batch\['corner_heat'\].*3\.9e\+17.*\[0, 1\].*roomB_pano7"),
    row("layout-corner-heat-nan", lambda: edited(layout_inputs(), layout_call, batch=lambda b: _set(
        b, corner_heat=with_px(b["corner_heat"], NAN, (0, 0, 5)))), None,
        verdict=ERROR, match=r"batch\['corner_heat'\].*(NaN|non-finite).*roomA_pano1"),
    row("layout-corner-heat-wrong-size", lambda: edited(layout_inputs(), layout_call, batch=lambda b: _set(
        b, corner_heat=b["corner_heat"][..., :9])), None,
        verdict=ERROR, match=r"corner_heat.*\(2, 1, 9\).*\(2, 1, 16\)"),
    row("layout-boundary-valid-wrong-shape", lambda: edited(layout_inputs(), layout_call, batch=lambda b: _set(
        b, boundary_valid=torch.ones(2, 1, 16, dtype=torch.bool))), None,
        verdict=ERROR, match=r"boundary_valid.*\(2, 1, 16\).*\(2, 2, 16\)"),
    row("layout-empty-batch-zero-flagged", lambda: layout_call(*layout_inputs(b=0)),
        flag("no_valid_boundary", "no_valid_corner", zero=True), verdict=OK),
    row("layout-nan-pred-propagates", lambda: edited(layout_inputs(), layout_call, out=lambda o: _set(
        o, boundary=with_px(o["boundary"], NAN, (0, 0, 1)))), nonfinite_loss, verdict=OK),
    row("layout-odd-width-1", lambda: layout_call(*layout_inputs(w=1)), finite, verdict=OK),
    row("layout-shape-mismatch", lambda: edited(layout_inputs(), layout_call, out=lambda o: _set(
        o, boundary=o["boundary"][..., :8])), None, verdict=ERROR, match=r"\(2, 2, 16\).*\(2, 2, 8\)"),
    # ------------------------------------------------------------------------------------------------ joint
    row("joint-label-14", lambda: edited(joint_inputs(), joint_call, batch=lambda b: _set(
        b, semantic=_labels_with(14))),
        None, verdict=ERROR, match=r"JointLoss.*\b14\b.*14 classes.*roomB_pano7"),
    row("joint-nan-depth-masked-flagged", lambda: edited(joint_inputs(), joint_call, batch=lambda b: _set(
        b, depth=with_px(b["depth"], NAN))), flag("nonfinite_depth"), verdict=OK),
    row("joint-millions-of-metres-warns-once", lambda: twice(lambda: joint_call(*joint_inputs(scale=1e6))),
        warns_once(r"not in metres"), verdict=OK),
    row("joint-all-invalid-both-flagged", lambda: edited(joint_inputs(), joint_call, batch=lambda b: _set(
        b, depth=torch.zeros_like(b["depth"]), semantic=torch.zeros_like(b["semantic"]))),
        flag("no_valid_depth", "no_valid_semantic", zero=True), verdict=OK),
    row("joint-empty-batch", lambda: joint_call(*joint_inputs(b=0)),
        flag("no_valid_depth", "no_valid_semantic", zero=True), verdict=OK),
    row("joint-depth-shape-mismatch", lambda: edited(joint_inputs(), joint_call, batch=lambda b: _set(
        b, depth=b["depth"][..., :4])), None, verdict=ERROR, match=r"\(2, 1, 8, 16\).*\(2, 1, 8, 4\)"),
    row("joint-semantic-vs-depth-size", lambda: edited(
        joint_inputs(), joint_call, out=lambda o: _set(o, semantic=o["semantic"][..., :4]),
        batch=lambda b: _set(b, semantic=b["semantic"][..., :4])), None,
        verdict=ERROR, match=r"outputs\['semantic'\] \(2, 14, 8, 4\).*outputs\['depth'\] \(2, 1, 8, 16\)"),
    row("joint-fractional-labels", lambda: edited(joint_inputs(), joint_call, batch=lambda b: _set(
        b, semantic=b["semantic"] + 0.25)), None, verdict=ERROR, match=r"JointLoss.*non-integer"),
    row("joint-float-integral-labels", lambda: edited(joint_inputs(), joint_call, batch=lambda b: _set(
        b, semantic=b["semantic"].double())), finite, verdict=OK),
    row("object-fn-label-14", lambda: (lambda: object_loss(_P, _T, _L, _labels_with(14))), None,
        verdict=ERROR, match=r"object_loss.*\b14\b.*14 classes"),
    row("object-fn-nan-target-masked", lambda: (lambda: object_loss(_P, with_px(_T, NAN), _L, _Y)), finite,
        verdict=OK),
]


@pytest.mark.parametrize("make, check, verdict, match", ROWS)
def test_loss_robustness(make, check, verdict, match):
    fn = make()
    if verdict != OK:
        expect(fn, verdict, match, error=(ValueError, KeyError))
        return
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = expect(fn, verdict, match)
    check(out, caught)


def test_table_covers_every_loss():
    names = [p.id for p in ROWS]
    for prefix in ("depth", "seg", "heat", "layout", "joint"):
        assert any(n.split("-", 1)[1].startswith(prefix) for n in names), prefix
    assert len(ROWS) >= 40
