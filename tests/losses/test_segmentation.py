"""Segmentation losses against hand computations (cross entropy, class weights, Recall loss)."""
import math

import numpy as np
import pytest
import torch

from omnidl.losses.segmentation import (SegmentationLoss, class_weights_from_frequencies, label_counts,
                                        recall_loss, weighted_cross_entropy)


def _example():
    torch.manual_seed(0)
    logits = torch.randn(2, 4, 3, 5, dtype=torch.float64)
    labels = torch.randint(0, 4, (2, 3, 5))
    labels[0, 0, :3] = 0
    return logits, labels


def _nll(logits, labels):
    lp = torch.log_softmax(logits, 1).numpy()
    lab = labels.numpy()
    b, h, w = np.indices(lab.shape)
    return -lp[b, lab, h, w], lab


def test_weighted_cross_entropy_by_hand():
    logits, labels = _example()
    w = torch.tensor([0.0, 1.0, 2.0, 0.5], dtype=torch.float64)
    nll, lab = _nll(logits, labels)
    known = lab != 0
    wn = w.numpy()[lab]
    expect = (wn * nll)[known].sum() / wn[known].sum()
    assert weighted_cross_entropy(logits, labels, w).item() == pytest.approx(expect, rel=1e-10)
    assert weighted_cross_entropy(logits, labels).item() == pytest.approx(nll[known].mean(), rel=1e-10)


def test_class_weights_closed_forms():
    counts = [100, 10, 30, 60]                       # class 0 (unknown) ignored -> p = 0.1, 0.3, 0.6
    p = np.array([0.1, 0.3, 0.6])
    for method, raw in (("inverse_log", 1 / np.log(1.02 + p)), ("inverse", 1 / p), ("median", 0.3 / p)):
        w = class_weights_from_frequencies(counts, method).numpy()
        assert w[0] == 0
        np.testing.assert_allclose(w[1:], raw / raw.mean(), rtol=1e-6)
    w = class_weights_from_frequencies([5, 0, 10, 30], "inverse")    # unseen class 1 -> largest seen weight
    assert w[1] == pytest.approx(w[2:].max().item())
    with pytest.raises(ValueError, match="method"):
        class_weights_from_frequencies(counts, "sqrt")


def test_label_counts():
    labels = torch.tensor([[0, 1, 1], [3, 3, 3]])
    assert label_counts(labels, 4).tolist() == [1, 2, 0, 3]


def test_recall_loss_by_hand():
    logits, labels = _example()
    nll, lab = _nll(logits, labels)
    pred = logits.argmax(1).numpy()
    known = lab != 0
    total = 0.0
    for c in range(1, 4):
        in_c = known & (lab == c)
        n_c = in_c.sum()
        if n_c == 0:
            continue
        tp = (in_c & (pred == c)).sum()
        fn = n_c - tp
        # N_c * log(geometric mean of p over class c) = sum of log p over class c
        total += fn / (fn + tp) * nll[in_c].sum()
    assert recall_loss(logits, labels).item() == pytest.approx(total / known.sum(), rel=1e-10)


def test_perfect_prediction_has_zero_recall_loss():
    labels = torch.tensor([[[1, 2], [3, 0]]])
    logits = torch.nn.functional.one_hot(labels, 4).permute(0, 3, 1, 2).double() * 5
    assert recall_loss(logits, labels).item() == 0.0


@pytest.mark.parametrize("kind", ["ce", "recall"])
def test_all_unknown_labels_give_zero(kind):
    logits = torch.randn(1, 4, 2, 3, requires_grad=True)
    loss = SegmentationLoss(kind, class_weights="batch")
    with pytest.warns(UserWarning, match="labelled"):
        total, terms = loss({"semantic": logits}, {"semantic": torch.zeros(1, 2, 3, dtype=torch.long)})
    assert total.item() == 0.0 and terms["no_valid_semantic"] == 1.0 and not math.isnan(terms["semantic"])
    total.backward()
    assert torch.isfinite(logits.grad).all()


def test_segmentation_loss_config_forms():
    logits, labels = _example()
    out, batch = {"semantic": logits}, {"semantic": labels}
    w = [0.0, 1.0, 2.0, 0.5]
    a, _ = SegmentationLoss("ce", class_weights=w)(out, batch)
    assert a.item() == pytest.approx(weighted_cross_entropy(logits, labels, torch.tensor(w)).item())
    freq = [5, 10, 20, 40]
    b, _ = SegmentationLoss("ce", class_frequencies=freq)(out, batch)
    assert b.item() == pytest.approx(
        weighted_cross_entropy(logits, labels, class_weights_from_frequencies(freq)).item(), rel=1e-6)
    batch_w = class_weights_from_frequencies(label_counts(labels, 4))
    c, _ = SegmentationLoss("ce", class_weights="batch")(out, batch)
    assert c.item() == pytest.approx(weighted_cross_entropy(logits, labels, batch_w).item(), rel=1e-6)
    with pytest.raises(ValueError, match="kind"):
        SegmentationLoss("dice")
    with pytest.raises(ValueError, match="logits"):
        SegmentationLoss()({"semantic": logits}, {"semantic": labels[:, :2]})
