"""Acceptance study helpers: hidden-wall runs and a tiny study run."""
import math

import numpy as np

from omnidl.apps.layout.acceptance import hidden_run, run_study, to_markdown
from omnidl.apps.layout.simulate import Room


def test_hidden_run_counts_consecutive_walls_no_column_sees():
    box = Room(np.array([[-2.0, -2.0], [3.0, -2.0], [3.0, 2.5], [-2.0, 2.5]]), 1.2, -1.4)
    assert hidden_run(box, 512, 0.8) == 0
    one = Room(np.array([[-1.5, -5.0], [6.5, -5.0], [6.5, -1.5], [2.3, -1.5], [2.3, 2.0], [-1.5, 2.0]]), 1.2, -1.4)
    assert hidden_run(one, 512, 0.8) == 1
    two = Room(np.array([[-1.5, -5.5], [6.5, -5.5], [6.5, -2.0], [2.3, -2.0], [2.3, 1.5], [-1.5, 1.5]]), 1.2, -1.4)
    assert hidden_run(two, 512, 0.8) == 2


def test_tiny_study_reports_every_room():
    rows = run_study(3, width=256, progress=False)
    assert [(r["world"], r["boundaries"]) for r in rows] == [
        ("manhattan", "sub-pixel"), ("manhattan", "rounded"), ("atlanta", "sub-pixel"), ("atlanta", "rounded")]
    for r in rows:
        assert r["rooms"] == 3 and r["failed"] == 0
        assert math.isfinite(r["ce_all"]) and 0 <= r["iou_3d_all"] <= 1            # fractions (issue 14)
    md = to_markdown(rows, 256, 1.0)
    assert md.count("\n| manhattan |") == 2 and md.count("\n| atlanta |") == 2 and "CE all" in md


def test_thesis_protocol_keeps_only_occlusion_free_rooms():
    rows = run_study(3, width=256, progress=False, occlusion_free=True)
    assert all(r["rooms"] == 3 and r["occluded"] == 0 and r["failed"] == 0 for r in rows)
    md = to_markdown(rows, 256, 1.0, occlusion_free=True)
    assert "Table 5.2 protocol" in md and "| – |" in md            # no occluded rooms: empty columns


def test_cli_prints_compact_thesis_columns_and_all_on_request(capsys):
    """Issue 18: the terminal tables had 21 columns; by default the thesis' columns, --all for everything."""
    from omnidl.apps.layout.acceptance import main
    args = ["--n", "1", "--width", "128", "--protocol", "all", "--no-progress"]
    assert main(args) == 0
    out = capsys.readouterr().out
    table = [line for line in out.splitlines() if line.startswith("|")]
    assert table[0].count("|") - 1 == 9                              # world, boundaries + 7 compact columns
    assert "CE (m) ↓" in table[0] and "3D IoU (%) ↑" in table[0] and "CEN (%) ↓" in table[0]
    assert len(table) == 2 + 4
    assert main(args + ["--all"]) == 0
    table = [line for line in capsys.readouterr().out.splitlines() if line.startswith("|")]
    assert table[0].count("|") - 1 == 21


def test_rows_are_fractions_and_only_the_printed_tables_are_percent():
    """Issue 14: run_study rows keep omnidl's units (CEN and IoU fractions); the "(%)" columns show them x 100."""
    row = {"world": "manhattan", "boundaries": "rounded", "rooms": 2, "occluded": 1, "hidden2": 0, "failed": 0,
           "height_err_max_m": 0.01, "ms_per_layout": 5.0, "ce_all": 0.0123, "cen_all": 0.00045,
           "iou_3d_all": 0.9876, "iou_3d_u2s_all": 0.99, "iou_2d_all": 0.9912}
    for tag in ("free", "occ", "hidden1", "hidden2"):
        row[f"ce_{tag}"], row[f"iou_3d_{tag}"] = 0.0123, 0.9876
    compact = to_markdown([row], 256, 1.0, all_columns=False).splitlines()
    head = next(line for line in compact if line.startswith("| world"))
    assert "CEN (%) ↓" in head and "3D IoU (%) ↑" in head and "2D IoU (%) ↑" in head
    assert compact[-1] == "| manhattan | rounded | 2 | 0 | 0.0123 | 0.045 | 98.76 | 99.12 | 5.0 |"
    full = to_markdown([row], 256, 1.0).splitlines()
    head = next(line for line in full if line.startswith("| world"))
    assert "3D IoU (%) all" in head and "CEN (%) all" in head and "2D IoU (%) all" in head
    assert full[-1].startswith("| manhattan | rounded | 2 | 1 | 0 | 0 | 0.0123 | 98.76 | 99.00 | 0.045 | 99.12 | 0.0123 |")
