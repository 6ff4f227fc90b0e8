"""A Python process that imports torch and omnidl once, then forks one child per command line (tests/test_readme.py).

A README command such as ``python train.py model=fredsnet ...`` spends ~3 s of CPU importing torch before it does
anything; the README has ~35 of them. The zygote pays that once: each command runs in a child forked from it, with
its own working directory, environment, ``sys.argv``, stdout/stderr files and exit status, exactly as the
interpreter runs it (``python SCRIPT``: ``runpy.run_path`` with the script's folder first on ``sys.path``;
``python -m MODULE``: ``runpy.run_module``; ``omnidl ...``: the console script's ``omnidl.apps.cli:main``), and the
interpreter's normal exit (``atexit``, flushing) ends it. Anything else (``torchrun``, shell operators, interpreter
options) is not a :func:`forkable` command and runs through ``bash`` as before.

Protocol (one JSON object per line): requests on stdin ``{"id", "argv", "cwd", "env", "stdout", "stderr"}``;
replies on stdout ``{"id", "pid"}`` when the child starts and ``{"id", "rc"}`` (its exit code; ``-N`` for signal N)
when it ends. The zygote never computes with torch before forking, so no intra-op thread pool exists to be
copied into a child, and it writes its replies with ``os.write`` so that no buffered output is inherited.

    python tests/zygote.py        # started by tests/test_readme.py's Runner, never by hand
"""
from __future__ import annotations

import json
import os
import runpy
import select
import shlex
import subprocess
import sys
import threading

#: modules every README command imports (the expensive part of starting one); not the ones run with ``-m``
PRELOAD = ("torch", "torchvision", "numpy", "cv2", "hydra", "omegaconf", "omnidl.engine", "omnidl.models",
           "omnidl.apps.train", "omnidl.apps.evaluate")
_SHELL = set("|&;<>()$`*?[]{}!")


def forkable(line: str) -> list[str] | None:
    """The argv of a command line the zygote runs (``python SCRIPT ...``, ``python -m MODULE ...``, ``omnidl ...``
    without shell operators or interpreter options), else None (run it through bash)."""
    try:
        argv = shlex.split(line)
    except ValueError:
        return None
    if not argv or any(set(tok) & _SHELL for tok in shlex.split(line, posix=False) if not tok.startswith(("'", '"'))):
        return None
    if argv[0] == "omnidl":
        return argv
    if argv[0] == "python" and len(argv) > 1:
        if argv[1] == "-m":
            return argv if len(argv) > 2 else None
        return None if argv[1].startswith("-") else argv
    return None


class Zygote:
    """The test side: starts ``python tests/zygote.py`` (its preloads imported with ``env``) and runs commands in it.

    ``run(argv, cwd, env, stdout, stderr, timeout)`` -> the exit code (thread-safe; a command past ``timeout``
    seconds is killed and raises ``subprocess.TimeoutExpired``, as ``subprocess.run`` does)."""

    def __init__(self, env: dict[str, str]) -> None:
        self._proc = subprocess.Popen([sys.executable, __file__], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                      env=env, cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        self._lock = threading.Lock()
        self._waiting: dict[str, dict] = {}
        self._next = 0
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self._proc.stdout:
            msg = json.loads(line)
            with self._lock:
                slot = self._waiting[msg["id"]]
            slot.update(msg)
            if "rc" in msg:
                slot["done"].set()
        with self._lock:                       # the zygote died: nothing running in it will report
            for slot in self._waiting.values():
                slot.setdefault("rc", -1)
                slot["done"].set()

    def run(self, argv: list[str], cwd: str, env: dict[str, str], stdout: str, stderr: str, timeout: float) -> int:
        with self._lock:
            self._next += 1
            rid = str(self._next)
            slot = self._waiting[rid] = {"done": threading.Event()}
            try:
                self._proc.stdin.write((json.dumps({"id": rid, "argv": argv, "cwd": cwd, "env": env,
                                                    "stdout": stdout, "stderr": stderr}) + "\n").encode())
                self._proc.stdin.flush()
            except OSError as e:
                raise RuntimeError(f"the zygote (tests/zygote.py) is gone (exit code {self._proc.poll()}): {e}; "
                                   "OMNIDL_README_ZYGOTE=0 runs the README commands without it") from e
        if not slot["done"].wait(timeout):
            if "pid" in slot:
                os.kill(slot["pid"], 9)
            raise subprocess.TimeoutExpired(argv, timeout)
        return int(slot["rc"])

    def close(self) -> None:
        try:
            self._proc.stdin.close()
            self._proc.wait(timeout=60)
        except (OSError, subprocess.TimeoutExpired):
            self._proc.kill()


_SHARED: Zygote | None = None
#: the environment of every command run through :func:`shared` (a command's own ``env`` is added to it)
BASE_ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}


def shared() -> Zygote:
    """This test process's zygote: started on first use (preloads imported with :data:`BASE_ENV`), closed at exit."""
    import atexit
    global _SHARED
    if _SHARED is None:
        _SHARED = Zygote(BASE_ENV)
        atexit.register(_SHARED.close)
    return _SHARED


def run_python(args: list[str], cwd: str | os.PathLike, env: dict[str, str] | None = None,
               timeout: float = 900) -> subprocess.CompletedProcess[str]:
    """``python *args`` (a script or ``-m MODULE``) in a child of :func:`shared`, returned as
    ``subprocess.run(..., capture_output=True, text=True)`` returns it."""
    import tempfile
    argv = ["python", *map(str, args)]
    with tempfile.TemporaryDirectory() as tmp:
        out, err = os.path.join(tmp, "stdout"), os.path.join(tmp, "stderr")
        rc = shared().run(argv, str(cwd), {**BASE_ENV, **(env or {})}, out, err, timeout)
        return subprocess.CompletedProcess(argv, rc, read_text(out), read_text(err))


def read_text(path: str | os.PathLike) -> str:
    """A child's stdout/stderr file ("" where it never started: the zygote had died)."""
    try:
        with open(path, errors="replace") as f:
            return f.read()
    except FileNotFoundError:
        return ""


def _run_child(req: dict) -> None:
    """In the forked child: become the command (never returns)."""
    code = 1
    try:
        os.chdir(req["cwd"])
        os.environ.clear()
        os.environ.update(req["env"])
        null = os.open(os.devnull, os.O_RDONLY)
        out = os.open(req["stdout"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        err = os.open(req["stderr"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(null, 0)
        os.dup2(out, 1)
        os.dup2(err, 2)
        argv = req["argv"]
        if argv[0] == "omnidl":
            sys.argv = list(argv)
            from omnidl.apps.cli import main
            sys.exit(main())
        if argv[1] == "-m":
            sys.argv = [argv[2], *argv[3:]]
            sys.path[0] = os.getcwd()
            runpy.run_module(argv[2], run_name="__main__", alter_sys=True)
        else:
            script = os.path.abspath(argv[1])
            sys.argv = list(argv[1:])
            sys.path[0] = os.path.dirname(script)
            runpy.run_path(script, run_name="__main__")
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        if not isinstance(e.code, (int, type(None))):
            print(e.code, file=sys.stderr)
    except BaseException:  # noqa: BLE001 - what an uncaught exception does at the top level of a fresh interpreter
        import traceback
        traceback.print_exc()
        code = 1
    sys.exit(code)


def _reply(obj: dict) -> None:
    os.write(1, (json.dumps(obj) + "\n").encode())


def main() -> None:
    for name in PRELOAD:
        try:
            __import__(name)
        except ImportError:  # an optional one missing: the commands that need it import it (and fail) themselves
            pass
    running: dict[int, str] = {}
    buf = b""
    stdin_open = True
    while stdin_open or running:
        ready, _, _ = select.select([0] if stdin_open else [], [], [], 0.05)
        if ready:
            chunk = os.read(0, 65536)
            if not chunk:
                stdin_open = False
            buf += chunk
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                req = json.loads(line)
                pid = os.fork()
                if pid == 0:
                    _run_child(req)
                running[pid] = req["id"]
                _reply({"id": req["id"], "pid": pid})
        while running:
            pid, status = os.waitpid(-1, os.WNOHANG)
            if pid == 0:
                break
            _reply({"id": running.pop(pid), "rc": os.waitstatus_to_exitcode(status)})


if __name__ == "__main__":
    main()
