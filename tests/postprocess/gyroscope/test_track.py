"""Gyroscope.track: the tilt (horizon network + fit) of the next frame in a worker thread while the photometric
steps of the current frame run; each result equals estimate() of that frame on the same thread count. Unpipelined
(or after the first frame of "auto" decides against the pipeline) each result is estimate() itself."""
import math

import pytest
import torch

from omnidl.data.horizon import horizon_heatmaps
from omnidl.geometry.rotations import random_tilt_rotation
from omnidl.models import create_model
from omnidl.utils.threads import limit_threads
from omnidl.postprocess.gyroscope.pipeline import Gyroscope, GyroscopeOptions, model_horizon_fn, pipelining_pays
from omnidl.postprocess.gyroscope.scene import procedural_panorama

OPTS = GyroscopeOptions(work_height=64, model_height=64, mpp_level=2, pvg_level=3, pvg_max_iter=5)


def _gyro():
    torch.manual_seed(0)
    run_net = model_horizon_fn(create_model("holinet", backbone="resnet18", width=0.125, conv="standard"), 64)

    def horizon_fn(images):  # the network runs in the worker; the maps are the upright ground truth (an
        run_net(images)      # untrained net gives no horizon)
        return tuple(m.expand(images.shape[0], -1, -1, -1) for m in horizon_heatmaps(torch.eye(3)[None], 32, 64))
    g = Gyroscope(horizon_fn, OPTS)
    g.set_reference(procedural_panorama(None, 64, 128, seed=1)[0])
    R = random_tilt_rotation(3, math.radians(20), generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    return g, [f[None] for f in procedural_panorama(R, 64, 128, seed=1)]


def _assert_equal(got, expect):
    assert len(got) == len(expect)
    for a, b in zip(got, expect):
        assert a.keys() == b.keys()
        for k in a:
            assert torch.equal(a[k], b[k]), k


def test_track_equals_estimate_frame_by_frame():
    g, frames = _gyro()
    before = torch.get_num_threads()
    with limit_threads(1):
        expect = [g.estimate(f) for f in frames]
    got = list(g.track(iter(frames), pipeline=True))
    assert torch.get_num_threads() == before
    _assert_equal(got, expect)


@pytest.mark.parametrize("pipeline", [True, False, "auto"])
def test_track_edge_cases(pipeline):
    g, frames = _gyro()
    before = torch.get_num_threads()
    assert list(g.track([], pipeline=pipeline)) == []
    gen = g.track(frames, pipeline=pipeline)
    next(gen)
    next(gen)
    gen.close()  # stopping early restores the thread setting
    assert torch.get_num_threads() == before
    with pytest.raises(ValueError):  # a bad frame raises when its result is reached, the earlier ones come out
        out = []
        for r in g.track([frames[0], torch.rand(1, 2, 64, 128)], pipeline=pipeline):
            out.append(r)
    assert len(out) == 1 and torch.get_num_threads() == before
    with pytest.raises(RuntimeError, match="set_reference"):
        next(Gyroscope(None, OPTS).track(frames))



def test_unpipelined_track_is_estimate():
    g, frames = _gyro()
    _assert_equal(list(g.track(frames, pipeline=False)), [g.estimate(f) for f in frames])


@pytest.mark.parametrize("decision", [True, False])
def test_auto_runs_the_first_frame_unpipelined_then_what_pays(decision, monkeypatch):
    import omnidl.postprocess.gyroscope.pipeline as P
    g, frames = _gyro()
    seen = []
    monkeypatch.setattr(P, "pipelining_pays", lambda *a: seen.append(a) or decision)
    got = list(g.track(frames))
    assert len(seen) == 1 and seen[0][2:] == (torch.get_num_threads(), 1) and min(seen[0][:2]) > 0
    first = g.estimate(frames[0])
    if decision:
        with limit_threads(1):
            rest = [g.estimate(f) for f in frames[1:]]
    else:
        rest = [g.estimate(f) for f in frames[1:]]
    _assert_equal(got, [first] + rest)
    assert list(g.track(frames[:1])) and len(seen) == 2        # one frame: decided, nothing left to pipeline


# (name, network s, rest s, threads now, threads per side, pipelined?)
DECISIONS = [
    ("HoLiNet-small: network 15 ms on 2 threads, rest 20 ms", 0.015, 0.020, 2, 1, True),
    ("HoLiNet-R50-Equi: network 62 ms on 2 threads, rest 25 ms", 0.062, 0.025, 2, 1, False),
    ("a one-thread process loses nothing to the split", 0.062, 0.025, 1, 1, True),
    ("one-thread network as slow as the whole frame: no gain", 0.020, 0.020, 2, 1, False),
    ("4 threads, 2 per side", 0.030, 0.040, 4, 2, True),
]


@pytest.mark.parametrize("name,net,rest,now,threads,verdict", DECISIONS, ids=[d[0] for d in DECISIONS])
def test_pipelining_pays(name, net, rest, now, threads, verdict):
    assert pipelining_pays(net, rest, now, threads) is verdict


def test_bad_pipeline_argument():
    g, frames = _gyro()
    with pytest.raises(ValueError, match="pipeline"):
        next(g.track(frames, pipeline="yes"))
