"""Object loss closed forms and the joint loss (Eq. 4.8): weights, single-task modes, invalid batches."""
import pytest
import torch

from omnidl.losses.depth import depth_loss, margin_loss
from omnidl.losses.joint import JointLoss, object_loss
from omnidl.losses.segmentation import weighted_cross_entropy


def _batch(seed=0, b=2, c=5, h=4, w=8):
    torch.manual_seed(seed)
    depth = torch.rand(b, 1, h, w, dtype=torch.float64) + 0.5
    depth[0, 0, 0, :3] = 0
    labels = torch.randint(0, c, (b, h, w))
    outputs = {"depth": (torch.rand(b, 1, h, w, dtype=torch.float64) + 0.5).requires_grad_(),
               "semantic": torch.randn(b, c, h, w, dtype=torch.float64, requires_grad=True)}
    return outputs, {"depth": depth, "semantic": labels}


def test_object_loss_gt_mode_closed_form():
    out, batch = _batch()
    p, g, lab = out["depth"], batch["depth"], batch["semantic"]
    valid = (g[:, 0] > 0) & (lab != 0)
    # with the true masks every valid pixel lands in exactly one class map:
    # (1/(C-1)) sum_c sum_{pixels of c} (g - p)^2 / N = sum (g - p)^2 / (N (C-1))
    expect = ((g - p)[:, 0][valid] ** 2).sum() / (valid.sum() * 4)
    torch.testing.assert_close(object_loss(p, g, out["semantic"], lab, mode="gt"), expect)


def test_object_loss_soft_mode_by_hand():
    out, batch = _batch(1, b=1, c=3, h=3, w=4)
    p, g, lab, logits = out["depth"][0, 0], batch["depth"][0, 0], batch["semantic"][0], out["semantic"][0]
    prob = logits.softmax(0)
    valid = (g > 0) & (lab != 0)
    assert valid.sum() >= 3
    total = torch.zeros((), dtype=torch.float64)
    for c in (1, 2):
        s = torch.zeros((), dtype=torch.float64)
        for i in range(3):
            for j in range(4):
                if valid[i, j]:
                    s += (g[i, j] * (lab[i, j] == c) - p[i, j] * prob[c, i, j]) ** 2
        total += s / valid.sum()
    got = object_loss(out["depth"], batch["depth"], out["semantic"], batch["semantic"], mode="soft")
    torch.testing.assert_close(got, total / 2)


def test_joint_loss_is_the_weighted_sum():
    out, batch = _batch()
    alphas = dict(alpha_semantic=8.0, alpha_depth=12.0, alpha_margin=0.001, alpha_object=4.0)
    total, terms = JointLoss(**alphas)(out, batch)
    seg = weighted_cross_entropy(out["semantic"], batch["semantic"])
    dep = depth_loss(out["depth"], batch["depth"])[0]
    mar = margin_loss(out["depth"], batch["depth"])
    obj = object_loss(out["depth"], batch["depth"], out["semantic"], batch["semantic"])
    torch.testing.assert_close(total, 8 * seg + 12 * dep + 0.001 * mar + 4 * obj)
    assert terms["total"] == pytest.approx(total.item())
    assert {"semantic", "depth", "depth_abs", "depth_grad", "margin", "object"} <= set(terms)
    total.backward()
    assert out["semantic"].grad.abs().sum() > 0 and out["depth"].grad.abs().sum() > 0


def test_single_task_modes_need_only_their_outputs():
    out, batch = _batch()
    d_total, d_terms = JointLoss(tasks=["depth"], alpha_margin=0)({"depth": out["depth"]}, {"depth": batch["depth"]})
    torch.testing.assert_close(d_total, 12 * depth_loss(out["depth"], batch["depth"])[0])
    assert "semantic" not in d_terms and "object" not in d_terms
    s_total, s_terms = JointLoss(tasks=["semantic"])({"semantic": out["semantic"]}, {"semantic": batch["semantic"]})
    torch.testing.assert_close(s_total, 8 * weighted_cross_entropy(out["semantic"], batch["semantic"]))
    # zero weights switch terms off too
    z_total, z_terms = JointLoss(alpha_semantic=0, alpha_object=0, alpha_margin=0)(out, batch)
    torch.testing.assert_close(z_total, d_total)
    with pytest.raises(KeyError, match="semantic"):
        JointLoss()({"depth": out["depth"]}, batch)
    with pytest.raises(ValueError, match="tasks"):
        JointLoss(tasks=["normals"])
    with pytest.raises(ValueError, match="no active term"):
        JointLoss(alpha_semantic=0, alpha_object=0, tasks=["semantic"])


def test_recall_variant():
    out, batch = _batch()
    total, terms = JointLoss(semantic_loss="recall")(out, batch)
    assert torch.isfinite(total)


def test_all_invalid_batch_is_zero_not_nan():
    out, _ = _batch()
    batch = {"depth": torch.zeros(2, 1, 4, 8, dtype=torch.float64), "semantic": torch.zeros(2, 4, 8, dtype=torch.long)}
    with pytest.warns(UserWarning):
        total, terms = JointLoss()(out, batch)
    assert total.item() == 0.0 and terms["no_valid_depth"] == 1.0 and terms["no_valid_semantic"] == 1.0
    total.backward()
    assert torch.isfinite(out["depth"].grad).all() and torch.isfinite(out["semantic"].grad).all()
