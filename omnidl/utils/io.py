"""Atomic file writes: every checkpoint and result file goes through these (temp file + rename).

A write goes to ``.<name>.<pid>@<host>.<random>.tmp`` in the target's folder (the writer's process id and host in
the name, so a process never mistakes another live writer's temp file for an orphan), is flushed and fsynced, gets the permissions
a plain ``open()`` would give (``0o666`` minus the process umask; ``mkstemp`` alone gives 0600), and is renamed
onto the target; the folder is then fsynced (best effort). A failed write removes its temp file and leaves the
old target untouched; a full disk is an ``OSError`` naming the file and the free space. Temp files orphaned by
a ``kill -9`` are removed by :func:`remove_stale_temps` (only those of dead processes on this host).

Also the two text formats every result file shares: JSON with numpy/torch values (:func:`json_default`)
and CSV from row dicts (:func:`rows_to_csv`).
"""
from __future__ import annotations

import csv
import errno
import io
import json
import os
import re
import shutil
import socket
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Callable

#: errno values that mean "the disk (or a quota / file-size limit) is full"
_FULL = {errno.ENOSPC, errno.EFBIG, getattr(errno, "EDQUOT", errno.ENOSPC)}


def current_umask() -> int:
    """The process umask (read from ``/proc/self/status`` when possible, which does not change it)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)  # no getter elsewhere: set and restore
    os.umask(mask)
    return mask


def _disk_full_error(path: Path, exc: BaseException) -> OSError | None:
    """An ``OSError`` naming ``path`` when ``exc`` means the disk or a size limit is full, else None."""
    code = getattr(exc, "errno", None)
    text = str(exc)
    if code not in _FULL and not any(s in text for s in ("No space left", "File too large", "iostream error",
                                                         "unexpected pos", "file write failed")):
        return None
    try:
        free = f"{shutil.disk_usage(path.parent).free / 2**20:.0f} MB free"
    except OSError:
        free = "free space unknown"
    err = OSError(code if code in _FULL else errno.ENOSPC,
                  f"could not write {path}: the disk is full or a file-size/quota limit was reached ({free}; "
                  f"{type(exc).__name__}: {text}); the previous {path.name}, if any, is unchanged")
    err.filename = str(path)
    return err


def this_host() -> str:
    """This machine's host name, reduced to ``[A-Za-z0-9-]`` (as it appears in temp and lock file names)."""
    return re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname()) or "localhost"


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this machine (a zombie counts as gone)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True   # exists, owned by someone else
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rsplit(b")", 1)[-1].split()[0] != b"Z"
    except (OSError, IndexError):
        return True


def temp_tag() -> str:
    """``<pid>@<host>``: the part of a temp file name that says which process writes it."""
    return f"{os.getpid()}@{this_host()}"


#: ``.<name>.<pid>@<host>.<random>.tmp`` (:func:`atomic_write`); ``.<name>.<random>.tmp`` from older versions
_TEMP = re.compile(r"^\.(?P<name>.+?)\.(?:(?P<pid>\d+)@(?P<host>[A-Za-z0-9-]+)\.)?(?P<rest>[^.]+)\.tmp$")


def _fsync_dir(folder: Path) -> None:
    """fsync a folder so a rename in it survives a power loss (best effort: not every OS/filesystem allows it)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> Path:
    """Call ``write(tmp_path)`` then rename the temp file onto ``path`` (same folder, so the rename is atomic).

    ``write`` should flush and fsync what it writes (the ``atomic_*`` helpers below do). The file gets
    ``0o666 & ~umask`` permissions. A full disk raises ``OSError`` naming ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{temp_tag()}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~current_umask())
        os.replace(tmp, path)
    except BaseException as e:
        if os.path.exists(tmp):
            os.unlink(tmp)
        full = _disk_full_error(path, e) if isinstance(e, Exception) else None
        if full is not None:
            raise full from e
        raise
    _fsync_dir(path.parent)
    return path


def remove_stale_temps(folder: str | os.PathLike, names: Sequence[str] | None = None) -> list[Path]:
    """Delete the temp files :func:`atomic_write` leaves when killed (``.<name>.<pid>@<host>.*.tmp``) in
    ``folder``; only those of ``names`` when given. A temp file of a live process, of this process, or of
    another host is kept (it may be a write in progress); one without a pid (older omnidl) is removed.
    Returns the removed paths."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    removed = []
    host = this_host()
    for p in folder.glob(".*.tmp"):
        m = _TEMP.match(p.name)
        if m is None or (names is not None and m["name"] not in names) or not p.is_file():
            continue
        if m["pid"] is not None:
            pid = int(m["pid"])
            if m["host"] != host or pid == os.getpid() or pid_alive(pid):
                continue
        try:
            p.unlink()
            removed.append(p)
        except FileNotFoundError:
            pass
    return removed


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    def w(tmp):
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
    return atomic_write(path, w)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj: Any, indent: int = 2) -> Path:
    return atomic_write_text(path, json.dumps(obj, indent=indent, sort_keys=False, default=json_default) + "\n")


def atomic_torch_save(path: str | os.PathLike, obj: Any) -> Path:
    """``torch.save(obj)`` atomically, flushed and fsynced."""
    import torch

    def w(tmp):
        with open(tmp, "wb") as f:
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
    return atomic_write(path, w)


def _numpy_globals() -> list:
    """What older omnidl checkpoints need besides tensors: the NumPy RNG state array (``np.random.get_state()``)."""
    import numpy as np
    try:
        from numpy._core.multiarray import _reconstruct
    except ImportError:  # numpy < 2
        from numpy.core.multiarray import _reconstruct
    return [_reconstruct, np.ndarray, np.dtype, type(np.dtype(np.uint32))]


def safe_torch_load(path: str | os.PathLike, map_location: Any = "cpu") -> Any:
    """``torch.load(path, weights_only=True)`` with the allow-list of :func:`_numpy_globals`: tensors, numbers,
    strings and containers only, so a file from the internet cannot run code. Anything else in the file, a
    truncated file or a non-torch file is a ``RuntimeError`` naming the file."""
    import torch
    try:
        with torch.serialization.safe_globals(_numpy_globals()):
            return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # truncated, not a torch file, or pickled code
        text = str(e)
        if "Weights only load failed" in text or "Unsupported global" in text:
            what = text[text.find("Unsupported global"):].split(" was not")[0] if "Unsupported global" in text else ""
            raise RuntimeError(f"could not read checkpoint {path}: it holds Python objects other than tensors, "
                               f"numbers and containers ({what or 'not allowed by weights_only=True'}); omnidl "
                               "refuses to unpickle them because that can run code. If you trust the file, load it "
                               "yourself with torch.load(weights_only=False) and re-save its state dict.") from e
        raise RuntimeError(f"could not read checkpoint {path}: {text.splitlines()[0] if text else type(e).__name__} "
                           "(truncated, or not a file written by torch.save)") from e


def atomic_imwrite(path: str | os.PathLike, image) -> Path:
    """Write an image with OpenCV atomically (format from the suffix of ``path``)."""
    import cv2
    path = Path(path)
    ok, buf = cv2.imencode(path.suffix or ".png", image)
    if not ok:
        raise IOError(f"could not encode image for {path}")
    return atomic_write_bytes(path, buf.tobytes())


def atomic_write_csv(path: str | os.PathLike, rows: Sequence[Mapping[str, object]]) -> Path:
    """Write :func:`rows_to_csv` of ``rows`` atomically."""
    return atomic_write_text(path, rows_to_csv(rows))


def rows_to_csv(rows: Sequence[Mapping[str, object]]) -> str:
    """CSV text of a list of row dicts: the union of their keys (first-seen order) as the header, ``""``
    where a row lacks a key, ``\n`` line ends."""
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: r.get(k, "") for k in keys})
    return buf.getvalue()


def json_default(o: Any):
    """``json.dumps(..., default=json_default)``: numpy scalars/arrays and tensors as numbers/lists, else ``str``."""
    try:
        import numpy as np
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:  # pragma: no cover
        pass
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)
