"""python -m omnidl.apps.report collects a sweep into a table with one row per job."""
import json

from omnidl.apps.report import main, write_report


def _job(root, i, code, metrics):
    d = root / str(i)
    (d / ".hydra").mkdir(parents=True)
    (d / ".hydra" / "config.yaml").write_text(f"name: {code}\nmodel: {{name: fredsnet}}\n")
    (d / ".hydra" / "overrides.yaml").write_text(f"- experiment={code}\n")
    (d / "metrics.json").write_text(json.dumps(metrics))


def test_report_table_rows_and_codes(tmp_path):
    codes = ["F-Std-CE-X", "X-Std-CE-X", "F-Equi-CE-X", "X-Equi-CE-X"]
    for i, c in enumerate(codes):
        _job(tmp_path, i, c, {"val": {"mre": 0.1 + i, "delta1": 0.9, "miou": 50.0 + i},
                              "rotation": {"0": {"mre": 0.1}, "10": {"mre": 0.2}}})
    written = write_report(tmp_path)
    md = written["markdown"].read_text()
    for c in codes:
        assert f"| {c} |" in md
    assert md.index("MRE") < md.index("δ¹") < md.index("mIoU")
    assert len(md.strip().splitlines()) == 2 + len(codes)
    assert written["rotation"].exists()


def test_report_cli_missing_folder(tmp_path, capsys):
    assert main([str(tmp_path / "nope")]) == 2
    assert "no such folder" in capsys.readouterr().err


def test_units_percent_only_in_the_printed_table(tmp_path, capsys):
    """Fractions in results.csv; mIoU/mAcc in percent in results.md, labelled (%); percent input is flagged."""
    import csv
    _job(tmp_path, 0, "F-Std-CE-X", {"final": {"val/mre": 0.2, "val/delta1": 0.61, "val/miou": 0.4237,
                                               "val/macc": 0.5}})
    _job(tmp_path, 1, "X-Std-CE-X", {"final": {"val/mre": 0.2, "val/delta1": 0.6, "val/miou": 42.0}})
    written = write_report(tmp_path)
    md = written["markdown"].read_text()
    assert "mIoU (%) ↑" in md and "mAcc (%) ↑" in md and "| F-Std-CE-X | 0.2000 | 0.6100 | 42.37 | 50.00 |" in md
    rows = list(csv.DictReader(open(written["csv"])))
    assert rows[0]["final/val/miou"] == "0.4237" and rows[0]["final/val/delta1"] == "0.6100"
    assert "val/miou = 42.0 is outside [0, 1]" in capsys.readouterr().err


def test_rotation_plot_one_panel_per_unit(tmp_path):
    from omnidl.apps.report import collect, rotation_panels
    rot = {str(a): {"mre": 0.1 + a / 100, "mae": 0.3, "rmse": 0.5, "delta1": 0.8, "miou": 0.4, "rmse_log": 0.2}
           for a in (0, 10, 20)}
    _job(tmp_path, 0, "F-Std-CE-X", {"val": {"mre": 0.1}, "rotation": rot})
    _job(tmp_path, 1, "F-Std-CE-X-r", {"val": {"mre": 0.1}, "rotation": {**rot, "bad": 3, "x": {"mre": 1}}})
    panels = rotation_panels(collect(tmp_path))
    assert panels == {"relative error": ["mre"], "metres": ["mae", "rmse"], "log metres": ["rmse_log"],
                      "fraction": ["delta1", "miou"]}
    written = write_report(tmp_path)
    assert written["rotation"].stat().st_size > 1000


def test_metrics_json_that_is_not_an_object_is_skipped(tmp_path, capsys):
    _job(tmp_path, 0, "F-Std-CE-X", {"val": {"mre": 0.1}})
    (tmp_path / "1").mkdir()
    (tmp_path / "1" / "metrics.json").write_text("[1, 2]")
    assert main([str(tmp_path)]) == 0
    assert "expected a JSON object" in capsys.readouterr().err


def test_layout_iou_and_cen_are_fractions_printed_in_percent(tmp_path, capsys):
    """Issue 14: layout IoU/CEN (LayoutMetrics, the layout hooks' layout_* scores, protocol groups) are fractions in
    metrics.json and results.csv; results.md shows them x 100 in (%) columns; a percent value is flagged."""
    import csv
    _job(tmp_path, 0, "H-NC", {"final": {"val/ce": 0.0123, "val/cen": 0.0021, "val/iou_3d": 0.9512, "val/iou_2d": 0.97,
                                         "val/layout_iou_3d": 0.95, "val/iou_2d@4": 0.9}})
    _job(tmp_path, 1, "H-NC-old", {"final": {"val/ce": 0.0123, "val/iou_3d": 95.12}})
    written = write_report(tmp_path)
    md = written["markdown"].read_text()
    assert "CE ↓" in md and "CEN (%) ↓" in md and "3D IoU (%) ↑" in md and "2D IoU (%) ↑" in md
    assert "| H-NC | 0.0123 | 0.21 | 95.12 | 97.00 |" in md
    rows = list(csv.DictReader(open(written["csv"])))
    assert rows[0]["final/val/iou_3d"] == "0.9512" and rows[0]["final/val/cen"] == "0.0021"
    err = capsys.readouterr().err
    assert "val/iou_3d = 95.12 is outside [0, 1]" in err
    assert main([str(tmp_path), "--all", "--overwrite"]) == 0
    out = capsys.readouterr().out
    assert "layout_iou_3d (%)" in out and "iou_2d@4 (%)" in out and "| 90.00 |" in out


def test_layout_units():
    from omnidl.apps.report import metric_unit
    assert [metric_unit(k) for k in ("val/iou_3d", "val/iou_2d@odd", "val/layout_iou_3d", "val/cen", "val/ce",
                                     "val/layout_ce", "val/edge_iou", "val/corner_error")] == \
        ["fraction"] * 4 + ["metres"] * 2 + ["fraction"] * 2


# --- issue 48: outputs never destroy data; names are text, never markup ---------------------------------------------

def test_report_never_overwrites_without_the_option(tmp_path, capsys):
    """A user's results.md in the sweep folder (or a previous report) is kept unless --overwrite."""
    _job(tmp_path, 0, "F-Std-CE-X", {"val": {"mre": 0.1}, "rotation": {"0": {"mre": 0.1}}})
    (tmp_path / "results.md").write_text("my notes")
    assert main([str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "results.md already exists" in err and "--overwrite" in err
    assert (tmp_path / "results.md").read_text() == "my notes"
    assert not (tmp_path / "results.csv").exists() and not (tmp_path / "rotation.png").exists()  # nothing written
    assert main([str(tmp_path), "--overwrite"]) == 0
    assert "F-Std-CE-X" in (tmp_path / "results.md").read_text()
    assert main([str(tmp_path), "--out", str(tmp_path / "results.csv")]) == 2
    assert "is an existing file" in capsys.readouterr().err


def test_report_names_cannot_break_the_markdown_table(tmp_path):
    code = "A|B <script>alert(1)</script> & x"
    _job(tmp_path, 0, "ok", {"val": {"mre": 0.1}})
    d = tmp_path / "1"
    (d / ".hydra").mkdir(parents=True)
    (d / ".hydra" / "config.yaml").write_text(f"name: {json.dumps(code)}\n")
    (d / "metrics.json").write_text(json.dumps({"val": {"mre": 0.2}}))
    md = write_report(tmp_path)["markdown"].read_text()
    rows = md.strip().splitlines()
    assert len(rows) == 4 and all(r.count(" | ") == rows[0].count(" | ") for r in rows[2:])   # one cell per column
    assert "<script>" not in md and "A\\|B &lt;script&gt;alert(1)&lt;/script&gt; &amp; x" in md


def test_markdown_cell_property():
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from omnidl.apps.report import markdown_cell

    @settings(max_examples=50, deadline=None, derandomize=True)
    @given(st.text(alphabet=st.sampled_from(list("ab|<>&\\\n\r\"' ")) | st.characters(), max_size=40))
    def check(text):
        cell = markdown_cell(text)
        assert not any(c in cell for c in "<>\n\r")
        assert "|" not in cell.replace("\\|", "")                    # every pipe is escaped
        import html
        back = html.unescape(cell.replace("\\|", "|").replace("\\\\", "\\"))
        assert back == text.replace("\n", " ").replace("\r", " ")
    check()
