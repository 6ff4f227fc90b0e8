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
        assert math.isfinite(r["ce_all"]) and 0 <= r["iou_3d_all"] <= 100
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
