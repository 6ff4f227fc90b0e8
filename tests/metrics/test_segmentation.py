"""mIoU / mAcc from a dataset-wide confusion matrix, unknown excluded, against hand counts."""
import math

import pytest
import torch

from omnidl.metrics.segmentation import SegmentationMetrics, confusion_matrix, scores_from_confusion


def test_confusion_matrix_by_hand():
    labels = torch.tensor([0, 1, 1, 2, 2, 2, 3])
    pred = torch.tensor([2, 1, 2, 2, 2, 0, 1])
    conf = confusion_matrix(pred, labels, 4)
    expect = torch.zeros(4, 4, dtype=torch.int64)
    for t, p in [(1, 1), (1, 2), (2, 2), (2, 2), (2, 0), (3, 1)]:    # the unknown-label pixel is dropped
        expect[t, p] += 1
    assert torch.equal(conf, expect)
    with pytest.raises(ValueError, match="predicted classes"):
        confusion_matrix(torch.tensor([5]), torch.tensor([1]), 4)


def test_scores_by_hand():
    labels = torch.tensor([0, 1, 1, 2, 2, 2, 3])
    pred = torch.tensor([2, 1, 2, 2, 2, 0, 1])
    s = scores_from_confusion(confusion_matrix(pred, labels, 4))
    # class 1: TP 1, FN 1, FP 1 (the class-3 pixel) -> IoU 1/3, acc 1/2
    # class 2: TP 2, FN 1 (predicted unknown), FP 1 -> IoU 2/4, acc 2/3
    # class 3: TP 0, FN 1 -> IoU 0, acc 0
    assert s["iou"][1:].tolist() == pytest.approx([1 / 3, 2 / 4, 0.0])
    assert s["acc"][1:].tolist() == pytest.approx([1 / 2, 2 / 3, 0.0])
    assert math.isnan(s["iou"][0])
    assert s["miou"] == pytest.approx((1 / 3 + 0.5 + 0) / 3)
    assert s["macc"] == pytest.approx((0.5 + 2 / 3 + 0) / 3)
    assert s["pixel_acc"] == pytest.approx(3 / 6)


def test_accumulates_over_batches_and_skips_absent_classes():
    metric = SegmentationMetrics(num_classes=5, class_names=["unknown", "a", "b", "c", "d"])
    labels = torch.tensor([[[1, 1], [2, 0]]])
    logits = torch.nn.functional.one_hot(torch.tensor([[[1, 2], [2, 3]]]), 5).permute(0, 3, 1, 2).float()
    metric.update({"semantic": logits}, {"semantic": labels})
    metric.update({"semantic": torch.tensor([[[2, 2]]])}, {"semantic": torch.tensor([[[2, 1]]])})
    out = metric.compute()
    # totals: class 1: TP 1, FN 2, FP 0 -> IoU 1/3 ; class 2: TP 2, FN 0, FP 2 -> IoU 1/2 ; classes 3, 4 absent
    assert out["miou"] == pytest.approx((1 / 3 + 1 / 2) / 2)
    assert out["macc"] == pytest.approx((1 / 3 + 1.0) / 2)
    assert out["iou/a"] == pytest.approx(1 / 3) and "iou/c" not in out and "iou/d" not in out
    metric.reset()
    assert math.isnan(metric.compute()["miou"])
    with pytest.raises(ValueError, match="channels"):
        metric.update({"semantic": torch.zeros(1, 3, 2, 2)}, {"semantic": labels})
