"""Units of the protocol's outputs: fractions in the rows (results.csv, summary.json) like every omnidl metric,
percent only in the printed thesis-style tables, in columns labelled (%) (issue 14)."""
from omnidl.apps.fisheye.tables import markdown_tables

ROWS = [{"stage": "BL", "dataset": "F195", "kernel": "Std", "mre": 0.25, "mae": 0.5, "rmse": 0.7, "rmse_log": 0.3,
         "delta1": 0.61, "delta2": 0.8, "delta3": 0.9, "miou": 0.4237, "macc": 0.5},
        {"stage": "BL", "dataset": "F195-R", "kernel": "Std", "mre": 0.3, "mae": 0.6, "rmse": 0.8,
         "delta1": 0.5, "miou": 0.31, "macc": 0.42, "covered_fraction": 0.85}]


def test_segmentation_printed_in_labelled_percent():
    md = markdown_tables(ROWS, ["depth", "semantic"], {})
    assert "| mIoU (%) ↑ | mAcc (%) ↑ |" in md
    assert "| BL | F195 | Std | 42.37 | 50.00 |" in md
    assert "| BL | F195-R | 0.3000 | 0.6000 | 0.8000 | 0.5000 | 31.00 | 42.00 | 0.850 |" in md
    # depth deltas stay fractions (as in Table 7.1), the rows are not modified
    assert "| 0.6100 |" in md and ROWS[0]["miou"] == 0.4237
