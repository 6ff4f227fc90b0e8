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
