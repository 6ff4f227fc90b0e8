"""benchmarks/_timing.py: the hypervisor steal share read from /proc/stat and the flags it raises."""
import pytest

from benchmarks import _timing

STAT = "cpu  {u} 0 {s} {i} 0 0 0 {st} 0 0\ncpu0 1 2 3 4 5 6 7 8 0 0\nintr 1 2 3\n"

# (text of /proc/stat, expected (steal, total) or None)
CPU_TIMES = [
    (STAT.format(u=100, s=50, i=800, st=50), (50, 1000)),
    ("cpu  1 2 3 4 5 6 7 8 9 10\n", (8, 36)),                       # guest fields are not added
    ("cpu0 1 2 3 4 5 6 7 8\n", None),                               # no all-CPU line
    ("cpu  1 2 3\n", None),                                         # too old a kernel: no steal field
    ("cpu  1 2 x 4 5 6 7 8\n", None),                               # garbled
    ("", None),
]


@pytest.mark.parametrize("text, expected", CPU_TIMES)
def test_cpu_times(text, expected):
    assert _timing.cpu_times(text) == expected


# (before, after, expected share)
SHARES = [
    ((50, 1000), (150, 2000), 0.10),
    ((50, 1000), (50, 2000), 0.0),
    ((50, 1000), (50, 1000), None),                                 # no elapsed ticks
    ((50, 1000), (40, 1500), 0.0),                                  # counter went back (new boot): not negative
    (None, (50, 1000), None),
    ((50, 1000), None, None),
]


@pytest.mark.parametrize("before, after, expected", SHARES)
def test_steal_share(before, after, expected):
    got = _timing.steal_share(before, after)
    assert got == (None if expected is None else pytest.approx(expected))


def _fake_clock(monkeypatch, readings):
    """steal_since_last sees the (monotonic s, (steal, total)) readings in order."""
    it = iter(readings)
    current = {}

    def tick():
        current["t"], current["ct"] = next(it)
        return current["t"]
    monkeypatch.setattr(_timing, "_clock", tick)
    monkeypatch.setattr(_timing, "cpu_times", lambda text=None: current["ct"])
    monkeypatch.setattr(_timing, "_CHECKS", [(0.0, (0, 1000))])


def test_steal_window_spans_the_last_check_at_least_a_second_old(monkeypatch):
    # 10 s timed loop with 30 % steal, closed by a check; a line printed right after it still reports the loop
    _fake_clock(monkeypatch, [(0.5, (0, 1100)), (10.5, (600, 3100)), (10.6, (600, 3110))])
    assert _timing.steal_since_last() == pytest.approx(0.0)          # import -> 0.5 s: no older check
    assert _timing.steal_since_last() == pytest.approx(600 / 2000)   # 0.5 s -> 10.5 s
    assert _timing.steal_since_last() == pytest.approx(600 / 2010)   # 0.5 s -> 10.6 s, not 10.5 -> 10.6


@pytest.mark.parametrize("steal, load, flags", [
    (0.02, 0.5, ()),
    (0.30, 0.5, ("STOLEN",)),
    (0.02, 3.0, ("LOADED",)),
    (0.30, 3.0, ("LOADED", "STOLEN")),
    (None, 0.5, ()),                                                 # no /proc/stat: no steal figure, no flag
])
def test_load_line_and_is_loaded_flag_steal(monkeypatch, steal, load, flags):
    monkeypatch.setattr(_timing, "steal_since_last", lambda min_window=1.0: steal)
    monkeypatch.setattr(_timing, "load1", lambda: load)
    line = _timing.load_line(2)
    for flag in ("LOADED", "STOLEN"):
        assert (f"** {flag}" in line) == (flag in flags), line
    assert ("hypervisor steal" in line) == (steal is not None)
    assert _timing.is_loaded(2) == bool(flags)
    assert _timing.is_loaded(2, steal=False) == ("LOADED" in flags)      # a set-up window's steal: not flagged


# (environment, words the tag must hold; () for no tag): figures taken with glibc keeping freed memory, with
# another allocator preloaded, or with PyTorch's huge-page allocations, say so on their TARGET line
ALLOCATORS = [
    ({}, ()),
    ({"MALLOC_MMAP_MAX_": "0", "MALLOC_TRIM_THRESHOLD_": "4000000000"},
     ("MALLOC_MMAP_MAX_=0", "MALLOC_TRIM_THRESHOLD_=4000000000", "judged on the default")),
    ({"MALLOC_MMAP_MAX_": ""}, ()),                                       # set but empty: glibc ignores it
    ({"GLIBC_TUNABLES": "glibc.malloc.mmap_max=0"}, ("GLIBC_TUNABLES=glibc.malloc.mmap_max=0",)),
    ({"GLIBC_TUNABLES": "glibc.pthread.rseq=0"}, ()),                     # a tunable outside malloc
    ({"LD_PRELOAD": "/usr/lib/x86_64-linux-gnu/libjemalloc.so.2"}, ("LD_PRELOAD=libjemalloc.so.2",)),
    ({"LD_PRELOAD": "/opt/lib/libfaketime.so"}, ()),
    ({"THP_MEM_ALLOC_ENABLE": "1"}, ("THP_MEM_ALLOC_ENABLE=1", "judged on the default")),   # PyTorch's huge pages
    ({"THP_MEM_ALLOC_ENABLE": "0"}, ()),
]


@pytest.mark.parametrize("environ, words", ALLOCATORS)
def test_allocator_tag(environ, words):
    tag = _timing.allocator_tag(environ)
    assert (tag == "") == (not words), tag
    for w in words:
        assert w in tag, tag


@pytest.mark.parametrize("target, ok, loaded, expected", [
    (None, None, False, "TARGET x: 2.00 ms = 1.25x conv (1.60 ms)"),
    ("<= 1.5x", True, False, "TARGET x: 2.00 ms = 1.25x conv (1.60 ms) (target <= 1.5x: met)"),
    ("<= 1.0x", False, True, "TARGET x: 2.00 ms = 1.25x conv (1.60 ms) (target <= 1.0x: MISSED) [taken under load]"),
])
def test_target_line(monkeypatch, target, ok, loaded, expected):
    # the line every benchmark prints (benchmarks/run_all.sh collects them), the allocator tag at its end
    for k in (*_timing.ALLOCATOR_VARS, "THP_MEM_ALLOC_ENABLE", "GLIBC_TUNABLES", "LD_PRELOAD"):
        monkeypatch.delenv(k, raising=False)
    assert _timing.target_line("x", "2.00 ms", 1.25, "conv (1.60 ms)", target, ok, loaded) == expected
    monkeypatch.setenv("THP_MEM_ALLOC_ENABLE", "1")
    tagged = _timing.target_line("x", "2.00 ms", 1.25, "conv (1.60 ms)", target, ok, loaded)
    assert tagged.startswith(expected + " [allocator: THP_MEM_ALLOC_ENABLE=1"), tagged
