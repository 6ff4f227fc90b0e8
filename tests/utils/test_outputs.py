"""The output policy helpers (omnidl/utils/outputs.py): guard_outputs, OutputClaims, unique_stems, RunLock."""
import json
import logging
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from omnidl.utils.io import this_host
from omnidl.utils.outputs import (LOCK_NAME, OutputClaims, OutputExistsError, OutputIsInputError, RunLock,
                                  RunLockedError, guard_outputs, is_within, same_file, unique_stems)

ROOT = Path(__file__).resolve().parents[2]


def test_an_output_that_is_an_input_is_refused_even_with_overwrite(tmp_path):
    src = tmp_path / "x.png"
    src.write_bytes(b"input")
    for out in (src, tmp_path / "." / "x.png", tmp_path / "sub" / ".." / "x.png"):
        with pytest.raises(OutputIsInputError, match=r"is the input file .*x\.png.*never overwritten"):
            guard_outputs([out], [src], overwrite=True)
    link = tmp_path / "hard.png"
    os.link(src, link)
    with pytest.raises(OutputIsInputError):
        guard_outputs([link], [src], overwrite=True)      # a hard link of the input is the input
    sym = tmp_path / "sym.png"
    sym.symlink_to(src)
    with pytest.raises(OutputIsInputError):
        guard_outputs([sym], [src], overwrite=True)


def test_an_existing_file_inside_an_input_folder_is_an_input(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    (data / "x_depth.png").write_bytes(b"ground truth")
    with pytest.raises(OutputIsInputError, match=r"x_depth\.png already exists inside the input folder"):
        guard_outputs([data / "x_depth.png"], [data], overwrite=True)
    guard_outputs([data / "x_pred.png"], [data])           # a new file beside the inputs is fine


def test_an_existing_output_needs_the_overwrite_option(tmp_path):
    out = tmp_path / "o.png"
    out.write_bytes(b"old")
    with pytest.raises(OutputExistsError, match=r"o\.png already exists.*add --force to replace"):
        guard_outputs([out], [], option="--force")
    guard_outputs([out], [], overwrite=True)
    with pytest.raises(OutputExistsError, match="is an existing folder"):
        guard_outputs([tmp_path], [], overwrite=True)


def test_two_outputs_that_are_one_file_case_insensitively_are_refused(tmp_path):
    with pytest.raises(ValueError, match=r"two outputs are the same file"):
        guard_outputs([tmp_path / "A.png", tmp_path / "a.png"])
    with pytest.raises(ValueError, match=r"two outputs are the same file"):
        guard_outputs([tmp_path / "a.png", tmp_path / "sub" / ".." / "a.png"])


def test_claims_refuse_a_second_write_and_an_older_result(tmp_path):
    claims = OutputClaims([tmp_path / "in.png"], overwrite=False, option="trainer.overwrite=true")
    claims.claim(tmp_path / "a.png")
    assert tmp_path / "a.png" in claims
    with pytest.raises(ValueError, match="would be written twice in this run"):
        claims.claim(tmp_path / "A.png")
    (tmp_path / "old.png").write_bytes(b"x")
    with pytest.raises(OutputExistsError, match=r"trainer\.overwrite=true"):
        claims.claim(tmp_path / "old.png")


@pytest.mark.parametrize("names, stems", [
    (["a.png", "b.jpg"], ["a", "b"]),
    (["a.png", "a.jpg"], ["a_png", "a_jpg"]),
    (["x/A.png", "y/a.png"], ["A_png", "a_png-2"]),
    (["a.png", "a.jpg", "a_png.tif"], ["a_png-2", "a_jpg", "a_png"]),   # a real a_png keeps its name
    (["r o o m.png", "zimmer ü.jpg", "部屋.png"], ["r o o m", "zimmer ü", "部屋"]),
    (["d1/a.png", "d2/a.png"], ["a_png", "a_png-2"]),
])
def test_unique_stems(names, stems):
    assert unique_stems(names) == stems
    assert unique_stems([Path(n) for n in names]) == stems


def test_a_lock_names_its_holder_and_is_released(tmp_path):
    with RunLock(tmp_path / "run", "search") as lock:
        info = json.loads(lock.path.read_text())
        assert info["pid"] == os.getpid() and info["host"] == this_host()
        with pytest.raises(RunLockedError, match=rf"is in use by another search: pid {os.getpid()} on host"):
            RunLock(tmp_path / "run").acquire()
    assert not (tmp_path / "run" / LOCK_NAME).exists()
    with RunLock(tmp_path / "run"):
        pass


def _locker(folder: Path) -> subprocess.Popen:
    code = textwrap.dedent(f"""
        import sys, time
        from omnidl.utils.outputs import RunLock
        lock = RunLock({str(folder)!r}, "training run").acquire()
        print("locked", flush=True)
        time.sleep(60)
    """)
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert p.stdout.readline().strip() == "locked"
    return p


def test_a_lock_held_by_another_process_stops_and_a_dead_ones_is_taken_over(tmp_path, caplog):
    p = _locker(tmp_path)
    try:
        with pytest.raises(RunLockedError, match=rf"in use by another training run: pid {p.pid} on host {this_host()}"):
            RunLock(tmp_path).acquire()
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait()
    assert (tmp_path / LOCK_NAME).exists()            # a kill -9 leaves the file behind
    with caplog.at_level(logging.WARNING, logger="omnidl.outputs"):
        with RunLock(tmp_path):
            assert json.loads((tmp_path / LOCK_NAME).read_text())["pid"] == os.getpid()
    assert f"taking over the lock left by pid {p.pid}" in caplog.text


def test_a_lock_file_of_a_dead_pid_is_taken_over_with_a_warning(tmp_path, caplog):
    (tmp_path / LOCK_NAME).write_text(json.dumps({"pid": 2**22 + 11, "host": this_host(), "started": "then"}))
    with caplog.at_level(logging.WARNING, logger="omnidl.outputs"):
        with RunLock(tmp_path):
            pass
    assert "no longer running" in caplog.text


def test_path_helpers(tmp_path):
    assert is_within(tmp_path / "a" / "b", tmp_path) and is_within(tmp_path, tmp_path)
    assert not is_within(tmp_path, tmp_path / "a")
    assert same_file(tmp_path / "x", tmp_path / "y" / ".." / "x") and not same_file(tmp_path / "x", tmp_path / "z")
