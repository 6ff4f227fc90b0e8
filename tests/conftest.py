"""Shared test fixtures and options.

``device`` and ``dtype`` fixtures (the kornia manner): a test that takes ``device`` runs once per device of
``--device`` (``cpu`` by default; ``cuda``, ``cuda:1``, ``all`` = cpu and cuda, or a comma list; CUDA runs
are skipped when no GPU is present), one that takes ``dtype`` once per dtype of ``--dtype`` (``float32``
and ``float64`` by default; ``float16``, ``bfloat16``, ``all`` or a comma list). A test that parametrises
``dtype``/``device`` itself keeps its own values.

    pytest                                # everything, on the CPU (what CI runs)
    pytest -m "not slow"                  # the fast unit run for local development
    pytest --device all --dtype float64   # also on CUDA, double precision only
"""
import os

import pytest
import torch

# Under pytest-xdist (the default `-n 2`) every worker gets its share of the CPUs as intra-op threads, and so do
# the subprocesses its tests start (OMP_NUM_THREADS): two workers with torch's default of one thread per core
# would run twice as many OpenMP threads as cores, and every small op's fork/join then waits for a descheduled
# thread (tests/cameras + tests/nn took 1.7-2.5x as long). Set before omnidl is imported, so that its
# `trainer.num_threads=0/auto` baseline (omnidl.engine.seed._INITIAL_THREADS) is the share too.
if os.environ.get("PYTEST_XDIST_WORKER_COUNT"):
    _SHARE = max(1, len(os.sched_getaffinity(0)) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"]))
    torch.set_num_threads(_SHARE)
    os.environ.setdefault("OMP_NUM_THREADS", str(_SHARE))

_DTYPES = {"float16": torch.float16, "bfloat16": torch.bfloat16, "float32": torch.float32, "float64": torch.float64}


def pytest_addoption(parser):
    parser.addoption("--device", default="cpu",
                     help="devices for tests taking the `device` fixture: cpu (default), cuda, cuda:N, all, "
                          "or a comma-separated list")
    parser.addoption("--dtype", default="float32,float64",
                     help="dtypes for tests taking the `dtype` fixture: float32,float64 (default), float16, "
                          "bfloat16, all, or a comma-separated list")


def _self_parametrised(metafunc, name: str) -> bool:
    for mark in metafunc.definition.iter_markers("parametrize"):
        names = mark.args[0]
        names = [n.strip() for n in names.split(",")] if isinstance(names, str) else list(names)
        if name in names:
            return True
    return False


def _devices(option: str) -> list:
    names = ["cpu", "cuda"] if option == "all" else [d.strip() for d in option.split(",") if d.strip()]
    params = []
    for name in names:
        dev = torch.device(name)
        marks = []
        if dev.type == "cuda" and not torch.cuda.is_available():
            marks = [pytest.mark.skip(reason="CUDA is not available")]
        params.append(pytest.param(dev, id=name, marks=marks))
    return params


def _dtypes(option: str) -> list:
    names = list(_DTYPES) if option == "all" else [d.strip() for d in option.split(",") if d.strip()]
    unknown = [n for n in names if n not in _DTYPES]
    if unknown:
        raise pytest.UsageError(f"--dtype: unknown {unknown}; expected some of {list(_DTYPES)} or all")
    return [pytest.param(_DTYPES[n], id=n) for n in names]


def pytest_generate_tests(metafunc):
    if "device" in metafunc.fixturenames and not _self_parametrised(metafunc, "device"):
        metafunc.parametrize("device", _devices(metafunc.config.getoption("--device")))
    if "dtype" in metafunc.fixturenames and not _self_parametrised(metafunc, "dtype"):
        metafunc.parametrize("dtype", _dtypes(metafunc.config.getoption("--dtype")))


@pytest.fixture
def single_thread():
    """Run a test on one intra-op thread: the tests use small tensors, for which thread-pool overhead dominates
    (and a busy shared CPU makes 2 threads many times slower than 1)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


#: the suite's longest files (tests/test_readme.py alone is ~4 min on two cores), started first: pytest-xdist hands
#: whole files to the workers in collection order (`--dist loadfile`), and the README, collected near the end, used
#: to start last and keep one worker busy for minutes after the other had finished.
LONGEST_FIRST = ("tests/test_readme.py", "tests/models/test_all_models_compile.py", "tests/models/test_export.py",
                 "tests/engine/test_signals.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    root = config.rootpath
    items.sort(key=lambda item: rank.get(item.path.relative_to(root).as_posix(), len(rank)))
