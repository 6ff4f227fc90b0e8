"""The one output policy of every command that writes files (train, evaluate, predict, reproject, synth, search,
report, convert).

Rules (each command applies them before it writes anything):

1. **Never write over an input.** An output that is the same file as an input (same path, a symlink or hard
   link to it, or the same name on a case-insensitive file system), or an *existing* file inside an input
   folder, is refused even with ``overwrite``: :class:`OutputIsInputError`.
2. **Never write over a previous run's results** unless the command resumes that run or is given its overwrite
   option (``--overwrite`` on the command line, ``trainer.overwrite=true`` for ``train.py``/``evaluate.py``):
   :class:`OutputExistsError`, naming the file and the option.
3. **Unique names** for inputs whose outputs would collide (``a.png`` + ``a.jpg``, ``A.png`` + ``a.png`` on a
   case-insensitive file system): :func:`unique_stems`.
4. **One process per output folder**: :class:`RunLock` writes ``<folder>/.omnidl.lock`` (pid, host, command)
   and holds an ``flock`` on it; a second process stops with :class:`RunLockedError` naming the holder. A lock
   left by a dead process on this host is taken over with a warning.
5. **Atomic writes** (temp file + rename, :mod:`omnidl.utils.io`): a kill never leaves a half-written output, and
   temp names carry the writer's pid and host, so two processes never delete each other's temp files.

API (small on purpose):

* :func:`guard_outputs` ``(outputs, inputs=(), overwrite=False, option="--overwrite")``: check a list of planned
  output paths against the rules 1-2 (and against each other) before any work; raises, else returns None.
* :class:`OutputClaims`: the same check one path at a time, for commands that learn their output names while
  they run (evaluation pictures); a path claimed twice in one run is a collision.
* :func:`unique_stems` ``(paths) -> list[str]``: output stems, unique case-insensitively, in input order.
* :class:`RunLock` ``(folder, what="run")``: context manager (``with RunLock(out): ...``).
* :func:`same_file`, :func:`is_within`: the path tests the rules use.
* ``atomic_write_bytes`` / ``atomic_write_text`` / ``atomic_write_json``: re-exported from :mod:`omnidl.utils.io`.
"""
from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import sys
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

from .io import atomic_write_bytes, atomic_write_json, atomic_write_text, pid_alive, this_host

__all__ = ["OutputExistsError", "OutputIsInputError", "RunLockedError", "guard_outputs", "OutputClaims",
           "unique_stems", "RunLock", "same_file", "is_within", "atomic_write_bytes", "atomic_write_text",
           "atomic_write_json", "LOCK_NAME", "OUTPUT_ERRORS"]

log = logging.getLogger("omnidl.outputs")

#: the lock file :class:`RunLock` keeps in a folder while a process writes there
LOCK_NAME = ".omnidl.lock"


class OutputExistsError(FileExistsError):
    """An output file already exists (a previous run's result) and the command was not told to overwrite it."""


class OutputIsInputError(OutputExistsError):
    """An output would replace an input file; refused even with the overwrite option."""


class RunLockedError(RuntimeError):
    """Another live process holds the lock of the output folder."""


#: what a command that writes reports as "error: ..." with exit status 2 (a refused output, a held folder)
OUTPUT_ERRORS = (FileExistsError, RunLockedError)


def _abs(p: str | os.PathLike) -> Path:
    return Path(os.path.abspath(os.fspath(p)))


def _real(p: str | os.PathLike) -> Path:
    """``p`` with symlinks resolved as far as they exist (an output need not exist yet)."""
    return Path(os.path.realpath(os.fspath(p)))


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether ``a`` and ``b`` name one file: equal real paths, or (both existing) the same inode: symlinks,
    hard links, a case-insensitive or bind-mounted file system."""
    if _real(a) == _real(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def is_within(path: str | os.PathLike, folder: str | os.PathLike) -> bool:
    """Whether ``path`` is ``folder`` or lies (at any depth) inside it, symlinks resolved."""
    p, f = _real(path), _real(folder)
    return p == f or f in p.parents


def _describe_inputs(inputs: Sequence[Path]) -> str:
    shown = ", ".join(str(p) for p in inputs[:3])
    return shown + (f" and {len(inputs) - 3} more" if len(inputs) > 3 else "")


def _conflict(out: Path, inputs: Sequence[Path], overwrite: bool, option: str) -> OutputExistsError | None:
    """The error for writing ``out`` under the rules 1-2, or None when it may be written."""
    if out.is_dir() and not out.is_symlink():
        return OutputExistsError(f"output {out} is an existing folder; expected a file path")
    for inp in inputs:
        if inp.is_dir():
            if out.exists() and is_within(out, inp):
                return OutputIsInputError(
                    f"output {out} already exists inside the input folder {inp}: it may be an input (e.g. a "
                    "ground-truth file) and is never overwritten, with or without "
                    f"{option}. Write the outputs to another folder")
        elif same_file(out, inp):
            return OutputIsInputError(f"output {out} is the input file {inp}; an input is never overwritten, with or "
                                      f"without {option}. Choose another output path")
    if (out.exists() or out.is_symlink()) and not overwrite:
        return OutputExistsError(f"output {out} already exists (a previous run's result?); add {option} to replace "
                                 "it, or choose another output path")
    return None


def guard_outputs(outputs: Iterable[str | os.PathLike], inputs: Iterable[str | os.PathLike] = (),
                  overwrite: bool = False, option: str = "--overwrite") -> None:
    """Check every planned output path before anything is written.

    Args:
        outputs: the files the command will write.
        inputs: the files *and folders* it reads; an existing file inside an input folder counts as an input.
        overwrite: whether existing outputs may be replaced (never an input).
        option: how the user says ``overwrite`` (named in the error), e.g. ``"--overwrite"`` or
            ``"trainer.overwrite=true"``.

    Raises:
        OutputIsInputError: an output is (or would replace) an input.
        OutputExistsError: an output exists and ``overwrite`` is false, or is a folder.
        ValueError: two outputs are the same file (compared case-insensitively, as on macOS/Windows).
    """
    ins = [_abs(p) for p in inputs]
    seen: dict[str, Path] = {}
    for o in outputs:
        out = _abs(o)
        key = os.path.normcase(str(_real(out))).casefold()
        if key in seen:
            raise ValueError(f"two outputs are the same file {seen[key]} and {out} (names are compared "
                             "case-insensitively, as a macOS/Windows file system does); give the inputs distinct names")
        seen[key] = out
        err = _conflict(out, ins, overwrite, option)
        if err is not None:
            raise err


class OutputClaims:
    """:func:`guard_outputs` one path at a time, for a run that learns its output names as it goes.

    ``claim(path)`` returns ``path`` when it may be written: it was not claimed before in this run (compared
    case-insensitively), it is not an input, and it did not exist before this run unless ``overwrite``.
    A path this run already wrote may not be claimed again (two samples with one output name)."""

    def __init__(self, inputs: Iterable[str | os.PathLike] = (), overwrite: bool = False,
                 option: str = "--overwrite") -> None:
        self.inputs = [_abs(p) for p in inputs]
        self.overwrite = overwrite
        self.option = option
        self._claimed: dict[str, Path] = {}

    def claim(self, path: str | os.PathLike) -> Path:
        out = _abs(path)
        key = os.path.normcase(str(_real(out))).casefold()
        if key in self._claimed:
            raise ValueError(f"output {out} would be written twice in this run (also as {self._claimed[key]}); "
                             "two inputs map to one output name")
        err = _conflict(out, self.inputs, self.overwrite, self.option)
        if err is not None:
            raise err
        self._claimed[key] = out
        return Path(path)

    def __contains__(self, path: str | os.PathLike) -> bool:
        return os.path.normcase(str(_real(_abs(path)))).casefold() in self._claimed


def unique_stems(paths: Sequence[str | os.PathLike]) -> list[str]:
    """One output stem per input path, unique case-insensitively, in input order; deterministic.

    A stem shared by no other input (case-insensitively) is kept (``room.png`` -> ``room``). Inputs sharing a stem
    get their extension added (``a.png``, ``a.jpg`` -> ``a_png``, ``a_jpg``; ``A.png``, ``a.png`` in two folders
    -> ``A_png``, ``a_png-2``); a name still taken gets ``-2``, ``-3``, ... in input order. Unicode, spaces and
    other characters are kept as they are (the caller sanitises if its format needs it)."""
    plain = [Path(os.fspath(p)).stem or Path(os.fspath(p)).name or "_" for p in paths]
    counts: dict[str, int] = {}
    for s in plain:
        counts[s.casefold()] = counts.get(s.casefold(), 0) + 1
    wanted = []
    for p, s in zip(paths, plain):
        suffix = Path(os.fspath(p)).suffix.lstrip(".")
        wanted.append(s if counts[s.casefold()] == 1 else (f"{s}_{suffix}" if suffix else s))
    taken: set[str] = set()
    out: list[str | None] = [None] * len(wanted)
    # plain stems first, so a derived name (a_png) never takes the place of a file really named a_png.tif
    order = sorted(range(len(wanted)), key=lambda i: (wanted[i] != plain[i], i))
    for i in order:
        stem, k = wanted[i], 2
        while stem.casefold() in taken:
            stem, k = f"{wanted[i]}-{k}", k + 1
        taken.add(stem.casefold())
        out[i] = stem
    return [s for s in out if s is not None]


class RunLock:
    """``with RunLock(folder):`` — only one process writes into ``folder`` at a time.

    Acquiring creates ``folder`` and ``folder/.omnidl.lock``, takes an exclusive non-blocking ``flock`` on it and
    writes ``{"pid", "host", "started", "command"}`` into it. When the lock is held by another live process:
    :class:`RunLockedError` naming the folder, that pid, host and command. A lock file whose ``flock`` is free
    (its process is gone: ``flock`` dies with the process) is taken over with a warning naming the old pid/host;
    so is one whose recorded pid is dead on this host (file systems without ``flock``). A lock file of another
    host that is not held is also taken over with a warning (its process is gone, or that file system's
    ``flock`` does not reach across hosts: then the check of the same folder from two hosts is best effort).
    Releasing removes the lock file. Not re-entrant: a second ``RunLock`` of one folder in the same process is
    refused too (per open file, like two processes).

    ``what`` names the job in messages (``"training run"``, ``"search"``, ...)."""

    def __init__(self, folder: str | os.PathLike, what: str = "run", name: str = LOCK_NAME) -> None:
        self.folder = Path(folder)
        self.path = self.folder / name
        self.what = what
        self._fd: int | None = None

    # -- helpers
    def _read(self, fd: int) -> dict:
        try:
            os.lseek(fd, 0, os.SEEK_SET)
            data = os.read(fd, 65536)
            obj = json.loads(data.decode("utf-8")) if data.strip() else {}
            return obj if isinstance(obj, dict) else {}
        except (OSError, ValueError):
            return {}

    def _holder(self, info: dict) -> str:
        if not info:
            return "an unknown process (the lock file is empty)"
        return (f"pid {info.get('pid')} on host {info.get('host')} (started {info.get('started', '?')}: "
                f"{info.get('command', '?')})")

    def acquire(self) -> "RunLock":
        if self._fd is not None:
            raise RunLockedError(f"{self.path}: this RunLock is already held")
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise OSError(e.errno, f"cannot create the output folder {self.folder}: {e.strerror or e}") from e
        for _ in range(5):  # the file may be replaced between open and flock by a releasing process: retry
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
            except OSError as e:
                raise OSError(e.errno, f"cannot create the lock file {self.path}: {e.strerror or e}") from e
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as e:
                info = self._read(fd)
                os.close(fd)
                if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    raise RunLockedError(
                        f"{self.folder} is in use by another {info.get('what', self.what)}: {self._holder(info)} "
                        f"holds {self.path}. "
                        f"Wait for it to finish, or write to another folder; if no such process is running, delete "
                        f"{self.path}") from None
                raise
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if not same:  # released (and removed) by its owner between our open and flock
                os.close(fd)
                continue
            info = self._read(fd)
            if info and not self._stale(info):
                os.close(fd)
                raise RunLockedError(
                    f"{self.folder} is in use by another {info.get('what', self.what)}: {self._holder(info)} holds "
                    f"{self.path} "
                    f"(its process is alive). Wait for it to finish, or write to another folder; if that process is "
                    f"not an omnidl command, delete {self.path}")
            if info:
                log.warning("%s: taking over the lock left by %s, which is no longer running", self.path,
                            self._holder(info))
            self._fd = fd
            self._write(fd)
            return self
        raise RunLockedError(f"{self.path}: could not take the lock (it kept changing); another {self.what} is "
                             "starting in the same folder")

    def _stale(self, info: dict) -> bool:
        """Whether the recorded holder is gone. We hold the ``flock`` here, so a live holder means a file system
        without ``flock`` (or pid reuse on this host)."""
        pid, host = info.get("pid"), info.get("host")
        if not isinstance(pid, int):
            return True
        if host != this_host():
            return True   # the flock was free: that process is gone (or flock does not cross hosts here)
        if pid == os.getpid():
            return False  # this process holds the folder through another RunLock
        return not pid_alive(pid)

    def _write(self, fd: int) -> None:
        info = {"pid": os.getpid(), "host": this_host(), "started": time.strftime("%Y-%m-%d %H:%M:%S"),
                "command": " ".join(sys.argv)[:500], "what": self.what}
        data = (json.dumps(info) + "\n").encode("utf-8")
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, data)
        try:
            os.fsync(fd)
        except OSError:
            pass

    def release(self) -> None:
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        try:
            try:
                if os.path.samestat(os.fstat(fd), os.stat(self.path)):
                    os.unlink(self.path)   # while still holding the flock: the next process opens a new file
            except FileNotFoundError:
                pass
        finally:
            os.close(fd)

    @property
    def held(self) -> bool:
        return self._fd is not None

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()

    def __del__(self) -> None:  # pragma: no cover - a forgotten release
        try:
            self.release()
        except Exception:
            pass

