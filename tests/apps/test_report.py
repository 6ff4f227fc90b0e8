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
