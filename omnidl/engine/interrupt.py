"""Ctrl-C / SIGTERM during training: finish the current step, write ``last.pt``, say how to resume.

:class:`StopRequest` replaces the SIGINT and SIGTERM handlers while the loop runs (main thread only): the
first signal only sets a flag that the loop checks after every step; a second one stops at once
(``KeyboardInterrupt``, nothing saved). The loop then raises :class:`TrainingInterrupted`, which
``train.py`` turns into a one-line message and exit status 130 (SIGINT) or 143 (SIGTERM).
"""
from __future__ import annotations

import logging
import signal
import threading

log = logging.getLogger("omnidl.engine")


class TrainingInterrupted(KeyboardInterrupt):
    """Training stopped by a signal after ``last.pt`` was written; ``command`` continues the run."""

    def __init__(self, signum: int, step: int, last: str, command: str):
        self.signum, self.step, self.last, self.command = signum, step, last, command
        super().__init__(f"{signal.Signals(signum).name}: stopped after step {step}; {last} written. "
                         f"Resume with:\n  {command}")

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


class StopRequest:
    """A flag set by SIGINT/SIGTERM (context manager; a no-op outside the main thread)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.signum: int | None = None
        self._old: dict[int, object] = {}

    def _handle(self, signum, frame) -> None:
        if self.signum is not None:  # second signal: stop now
            self.restore()
            raise KeyboardInterrupt(f"{signal.Signals(signum).name} again: stopping without saving")
        self.signum = signum
        log.warning("%s received: finishing the current step, then writing last.pt (press Ctrl-C again to stop "
                    "at once without saving)", signal.Signals(signum).name)

    def __enter__(self) -> "StopRequest":
        if threading.current_thread() is threading.main_thread():
            for s in self.SIGNALS:
                self._old[s] = signal.getsignal(s)
                signal.signal(s, self._handle)
        return self

    def restore(self) -> None:
        for s, h in self._old.items():
            signal.signal(s, h)
        self._old.clear()

    def __exit__(self, *exc) -> None:
        self.restore()

    @property
    def requested(self) -> bool:
        return self.signum is not None
