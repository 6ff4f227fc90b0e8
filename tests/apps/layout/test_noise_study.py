"""Noise study CLI: exact at zero noise, errors grow with noise, files written."""
import numpy as np

from omnidl.apps.layout import noise_study


def test_noise_study_small_run(tmp_path):
    res = noise_study.run(rooms=2, sigmas=(0.0, 2.0), width=256, reps=1)
    for s in noise_study.SOLVERS:
        if np.isnan(res[s]["ce"][0]):
            continue
        assert res[s]["ce"][0] < 1e-6 and res[s]["depth"][0] < 1e-6
        assert res[s]["depth"][1] > res[s]["depth"][0]
    assert res["atlanta"]["dir"] == [0.0, 0.0]
    assert noise_study.main(["--rooms", "2", "--sigmas", "0", "1", "--width", "256", "--reps", "1",
                             "--out", str(tmp_path)]) == 0
    assert (tmp_path / "noise_study.md").read_text().count("|") > 20 and (tmp_path / "noise_study.png").exists()
