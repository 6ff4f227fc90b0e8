"""Atomic writes and the shared JSON/CSV formats of result files."""
import csv
import io
import json

import numpy as np
import pytest
import torch

from omnidl.utils.io import atomic_write, atomic_write_csv, atomic_write_json, json_default, rows_to_csv


def test_failed_write_leaves_the_old_file_and_no_temp_file(tmp_path):
    path = atomic_write_json(tmp_path / "r" / "m.json", {"a": 1})

    def broken(tmp):
        with open(tmp, "w") as f:
            f.write("half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(path, broken)
    assert json.loads(path.read_text()) == {"a": 1} and [p.name for p in path.parent.iterdir()] == ["m.json"]


def test_rows_to_csv_takes_the_union_of_keys_in_first_seen_order(tmp_path):
    rows = [{"name": "a", "mae": 0.5}, {"name": "b", "acc": 1.0, "mae": 0.25}]
    text = rows_to_csv(rows)
    assert text.splitlines()[0] == "name,mae,acc" and "\r" not in text
    back = list(csv.DictReader(io.StringIO(text)))
    assert back == [{"name": "a", "mae": "0.5", "acc": ""}, {"name": "b", "mae": "0.25", "acc": "1.0"}]
    assert atomic_write_csv(tmp_path / "t.csv", rows).read_text() == text


def test_json_default_writes_numpy_and_torch_values():
    obj = {"f": np.float32(1.5), "a": np.arange(3), "t": torch.tensor([[1.0, 2.0]], requires_grad=True),
           "s": torch.tensor(3), "p": object}
    back = json.loads(json.dumps(obj, default=json_default))
    assert back["f"] == 1.5 and back["a"] == [0, 1, 2] and back["t"] == [[1.0, 2.0]] and back["s"] == 3
    assert back["p"] == str(object)


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_written_files_follow_the_process_umask(tmp_path, umask, mode):
    import os

    from omnidl.utils.io import atomic_torch_save, atomic_write_text, current_umask
    old = os.umask(umask)
    try:
        assert current_umask() == umask
        a = atomic_write_text(tmp_path / "a.txt", "x")
        b = atomic_torch_save(tmp_path / "b.pt", {"w": torch.zeros(2)})
    finally:
        os.umask(old)
    assert (a.stat().st_mode & 0o777, b.stat().st_mode & 0o777) == (mode, mode)


def test_torch_save_is_fsynced(tmp_path, monkeypatch):
    import os

    from omnidl.utils.io import atomic_torch_save
    synced = []
    real = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(fd), real(fd)))
    atomic_torch_save(tmp_path / "c.pt", {"w": torch.ones(3)})
    assert len(synced) >= 1  # the file (and, best effort, its folder)
    assert torch.equal(torch.load(tmp_path / "c.pt", weights_only=True)["w"], torch.ones(3))


def test_full_disk_names_the_file_and_keeps_the_old_one(tmp_path):
    import errno

    path = atomic_write_json(tmp_path / "m.json", {"a": 1})

    def full(tmp):
        with open(tmp, "wb") as f:
            f.write(b"12")
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError, match=r"could not write .*m\.json: the disk is full") as info:
        atomic_write(path, full)
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(path)
    assert json.loads(path.read_text()) == {"a": 1} and [p.name for p in tmp_path.iterdir()] == ["m.json"]


def test_file_size_limit_during_torch_save_is_a_clear_error(tmp_path):
    """A real write failure (RLIMIT_FSIZE, the usual disk-full stand-in) inside torch.save, in a subprocess."""
    import subprocess
    import sys
    code = (
        "import resource, signal, torch\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "from omnidl.utils.io import atomic_torch_save\n"
        f"atomic_torch_save({str(tmp_path / 'big.pt')!r}, {{'w': torch.zeros(1)}})\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))\n"
        "try:\n"
        f"    atomic_torch_save({str(tmp_path / 'big.pt')!r}, {{'w': torch.zeros(1_000_000)}})\n"
        "except OSError as e:\n"
        "    print('ERR', e)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert "could not write" in out.stdout and "big.pt" in out.stdout, out.stdout + out.stderr
    assert [p.name for p in tmp_path.iterdir()] == ["big.pt"]  # no temp file left
    assert torch.load(tmp_path / "big.pt", weights_only=True)["w"].numel() == 1  # the old file is intact


def test_remove_stale_temps_only_touches_named_temp_files(tmp_path):
    from omnidl.utils.io import remove_stale_temps
    for name in (".last.pt.ab12.tmp", ".best.pt.x.tmp", ".other.json.y.tmp", "last.pt", "keep.tmp"):
        (tmp_path / name).write_bytes(b"x")
    removed = remove_stale_temps(tmp_path, ["last.pt", "best.pt"])
    assert sorted(p.name for p in removed) == [".best.pt.x.tmp", ".last.pt.ab12.tmp"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [".other.json.y.tmp", "keep.tmp", "last.pt"]
    assert remove_stale_temps(tmp_path / "missing") == []


class _Code:
    def __reduce__(self):
        return (print, ("ran code",))


def test_safe_torch_load_refuses_pickled_code_and_names_the_file(tmp_path, capsys):
    from omnidl.utils.io import safe_torch_load
    torch.save({"w": torch.ones(2), "x": _Code()}, tmp_path / "x.pt")
    with pytest.raises(RuntimeError, match=r"x\.pt: it holds Python objects"):
        safe_torch_load(tmp_path / "x.pt")
    assert "ran code" not in capsys.readouterr().out
    torch.save({"w": torch.ones(2), "n": [1, 2.5, "a", None]}, tmp_path / "ok.pt")
    assert safe_torch_load(tmp_path / "ok.pt")["n"] == [1, 2.5, "a", None]
