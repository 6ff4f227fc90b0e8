"""On-disk formats: depth coding round trip (the writer CLI's tests are in tests/apps/test_synth_cli.py)."""
import numpy as np
import pytest
import torch

from omnidl.synth.export import decode_depth_24bit, encode_depth_24bit


@pytest.fixture(autouse=True)
def _threads():
    torch.set_num_threads(1)


def test_depth_coding_roundtrip_closed_form():
    d = np.concatenate([np.linspace(0, 10, 10001), np.random.default_rng(0).uniform(0, 10, 5000)])
    rgb = encode_depth_24bit(d)
    assert np.abs(decode_depth_24bit(rgb) - d).max() < 10 / 255 ** 3
    # the dataset's formula, written out: d = R*10/255 + G*10/255^2 + B*10/255^3
    r, g, b = rgb[..., 0].astype(float), rgb[..., 1].astype(float), rgb[..., 2].astype(float)
    assert np.allclose(r * 10 / 255 + g * 10 / 255 ** 2 + b * 10 / 255 ** 3, decode_depth_24bit(rgb))
