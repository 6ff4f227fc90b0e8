"""models/_weights: local weight files load through weights_only=True; pickled code is refused, never run."""
import pickle

import pytest
import torch
from torch import nn

from omnidl.models._weights import load_weights, read_state_dict


class _Boom:
    def __reduce__(self):                      # unpickling this would call os.system
        import os
        return (os.system, ("echo pwned",))


@pytest.mark.parametrize("wrap", ["model", "state_dict", "bare"])
def test_checkpoint_layouts_load(tmp_path, wrap):
    net = nn.Linear(3, 2)
    sd = {f"module.{k}": v for k, v in net.state_dict().items()}
    obj = {"model": sd, "step": 3} if wrap == "model" else {"state_dict": sd} if wrap == "state_dict" else sd
    torch.save(obj, tmp_path / "w.pt")
    other = nn.Linear(3, 2)
    load_weights(other, tmp_path / "w.pt")
    assert all(torch.equal(a, b) for a, b in zip(net.state_dict().values(), other.state_dict().values()))


def test_pickled_code_is_refused_and_not_run(tmp_path, capfd):
    with open(tmp_path / "evil.pt", "wb") as f:
        pickle.dump({"model": {"w": torch.zeros(1)}, "x": _Boom()}, f, protocol=2)
    with pytest.raises(RuntimeError, match="evil.pt"):
        read_state_dict(tmp_path / "evil.pt")
    assert "pwned" not in capfd.readouterr().out


def test_missing_and_junk_files_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.pt"):
        read_state_dict(tmp_path / "nope.pt")
    (tmp_path / "junk.pt").write_bytes(b"not torch")
    with pytest.raises(RuntimeError, match="junk.pt"):
        read_state_dict(tmp_path / "junk.pt")
