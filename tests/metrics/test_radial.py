"""Metrics binned by the distance to the principal point: hand-computed bins, mean ± std over images."""
import math

import numpy as np
import pytest
import torch

from omnidl.metrics.radial import RadialMetrics, plot_radial, radial_bin_edges
from omnidl.utils.io import rows_to_csv
from omnidl.metrics.segmentation import SegmentationMetrics


def make_batch():
    """2 images 2x4: columns 0-1 radius 0.5 (bin 0), columns 2-3 radius 1.5 (bin 1)."""
    radius = torch.tensor([[0.5, 0.5, 1.5, 1.5]] * 2).expand(2, 1, 2, 4)
    gt = torch.full((2, 1, 2, 4), 2.0)
    gt[1, 0, 0, 3] = 0.0                                   # one invalid pixel in image 1, bin 1
    rel = torch.tensor([[0.1, 0.1, 0.5, 0.5], [0.3, 0.3, 0.2, 0.2]])   # relative error per image/column
    pred = gt * (1 + rel[:, None, None, :])
    labels = torch.tensor([[[1, 2, 1, 2], [1, 2, 1, 2]], [[1, 1, 2, 0], [2, 2, 1, 2]]])
    pred_lab = torch.tensor([[[1, 2, 2, 1], [1, 2, 1, 2]], [[1, 1, 2, 2], [2, 2, 2, 2]]])
    logits = torch.nn.functional.one_hot(pred_lab, 3).permute(0, 3, 1, 2).float()
    return {"depth": pred, "semantic": logits}, {"depth": gt, "semantic": labels, "radius": radius}


def test_depth_bins_mean_and_std():
    out, batch = make_batch()
    m = RadialMetrics(edges=[0, 1, 2], num_classes=3)
    m.update(out, batch)
    rows = m.table()
    assert [r["r_mid"] for r in rows] == [0.5, 1.5]
    assert rows[0]["mre_mean"] == pytest.approx(0.2)
    assert rows[0]["mre_std"] == pytest.approx(np.std([0.1, 0.3], ddof=1))
    assert rows[1]["mre_mean"] == pytest.approx(0.35)
    assert rows[1]["mae_mean"] == pytest.approx((1.0 + 0.4) / 2)
    assert rows[1]["delta1_mean"] == pytest.approx(0.5)    # image 0: 1.5 > 1.25 -> 0; image 1: 1.2 -> 1
    assert rows[0]["pixels"] == 8 and rows[1]["pixels"] == 7
    assert rows[0]["images"] == 2


def test_segmentation_bins_against_segmentation_metrics():
    out, batch = make_batch()
    m = RadialMetrics(edges=[0, 1, 2], tasks=["semantic"], num_classes=3)
    m.update(out, batch)
    rows = m.table()
    for b, cols in ((0, slice(0, 2)), (1, slice(2, 4))):
        per_image = []
        for i in range(2):
            ref = SegmentationMetrics(num_classes=3)
            ref.update({"semantic": out["semantic"][i:i + 1, :, :, cols]}, {"semantic": batch["semantic"][i:i + 1, :, cols]})
            per_image.append(ref.compute()["miou"])
        assert rows[b]["miou_mean"] == pytest.approx(np.mean(per_image))
        assert rows[b]["miou_std"] == pytest.approx(np.std(per_image, ddof=1))
        ref = SegmentationMetrics(num_classes=3)
        ref.update({"semantic": out["semantic"][:, :, :, cols]}, {"semantic": batch["semantic"][:, :, cols]})
        assert rows[b]["miou_all"] == pytest.approx(ref.compute()["miou"])
    assert rows[0]["miou_all"] == 1.0


def test_default_edges_from_first_batch_and_fixed_radius_map():
    out, batch = make_batch()
    r = batch.pop("radius")[0, 0]
    m = RadialMetrics(num_bins=3, tasks=["depth"], radius=r)
    m.update(out, batch)
    assert m.edges[0] == 0 and m.edges[-1] == pytest.approx(1.5)
    assert len(m.table()) == 3 and m.table()[1]["pixels"] == 0
    assert math.isnan(m.table()[1]["mre_mean"])
    flat = m.compute()
    assert flat["radial/mre_mean/bin0"] == pytest.approx(0.2)


def test_errors_and_outputs(tmp_path):
    out, batch = make_batch()
    batch.pop("radius")
    with pytest.raises(KeyError, match="radius"):
        RadialMetrics(edges=[0, 1]).update(out, batch)
    with pytest.raises(ValueError, match="increasing"):
        RadialMetrics(edges=[0, 0])
    assert radial_bin_edges(10, 2) == [0, 5, 10]
    out, batch = make_batch()
    m = RadialMetrics(edges=[0, 1, 2], num_classes=3)
    m.update(out, batch)
    text = rows_to_csv(m.table())
    assert text.splitlines()[0].startswith("r_lo,r_hi,r_mid,pixels")
    p = plot_radial({"Std": m.table(), "Calib": m.table()}, ["mre", "miou"], tmp_path / "r.png")
    assert p.stat().st_size > 1000


@pytest.mark.parametrize("metrics", [["mre"], ["mre", "delta1"], ["mre", "delta1", "mre", "delta1", "mre"]])
def test_plot_labels_stay_inside_the_figure(tmp_path, monkeypatch, metrics):
    """The x-axis labels, tick labels and titles of every panel are drawn inside the figure (none cut off)."""
    import matplotlib.pyplot as plt
    figs = []
    close = plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: figs.append(fig))
    rows = [{"r_mid": r, "mre_mean": 0.1 + r / 1e3, "mre_std": 0.02, "delta1_mean": 0.9, "delta1_std": 0.03}
            for r in (20.0, 60.0, 100.0)]
    plot_radial({"A": rows, "B": rows}, metrics, tmp_path / "r.png", title="t" if len(metrics) != 2 else "")
    fig = figs[0]
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    box = fig.bbox
    for ax in fig.axes[:len(metrics)]:
        assert ax.xaxis.label.get_text() == "distance to the principal point (px)"
        e = ax.get_tightbbox(r)             # what is drawn of the panel: ticks, tick labels, axis labels, title
        assert box.x0 - 0.5 <= e.x0 and e.x1 <= box.x1 + 0.5 and box.y0 - 0.5 <= e.y0 and e.y1 <= box.y1 + 0.5, (e, box)
    close(fig)
