"""The three verdicts a bad input may get, and the row helper every robustness table uses.

A robustness table is a list of ``row(...)`` entries; each row names the input, the verdict it must get and,
for errors and skips, a regular expression the message must match (it should name the file, field or value
and say what was expected):

    ERROR  a clear exception (``ValueError``, ``FileNotFoundError``, ``OSError`` ...) whose message matches;
    SKIP   a flagged skip: the sample / file is left out with a warning whose message matches;
    OK     handled correctly; the test checks the value it returns.

``tests/robustness/conftest.py`` counts the rows by verdict at the end of a run (``-rA`` not needed).
"""
from __future__ import annotations

import re
import warnings
from typing import Any, Callable

import pytest

ERROR = "error"
SKIP = "skip"
OK = "ok"
VERDICTS = (ERROR, SKIP, OK)


def row(name: str, *values: Any, verdict: str, match: str | None = None, marks=()) -> Any:
    """One table row: ``pytest.param(*values, verdict, match, id="<verdict>-<name>")``.

    The test function takes the values, then ``verdict`` and ``match``."""
    if verdict not in VERDICTS:
        raise ValueError(f"verdict {verdict!r}: expected one of {VERDICTS}")
    if verdict != OK and not match:
        raise ValueError(f"row {name!r}: an {verdict} row needs a message pattern")
    return pytest.param(*values, verdict, match, id=f"{verdict}-{name}", marks=marks)


def expect(fn: Callable[[], Any], verdict: str, match: str | None,
           error: type[BaseException] | tuple = Exception) -> Any:
    """Run ``fn`` and check it gets ``verdict``; returns ``fn()``'s value for OK and SKIP rows.

    ERROR: ``fn`` raises ``error`` with a message matching ``match`` (``re.search``, case-insensitive).
    SKIP:  ``fn`` returns and emits at least one warning whose message matches ``match``.
    OK:    ``fn`` returns without raising (the caller checks the value)."""
    if verdict == ERROR:
        with pytest.raises(error) as info:
            fn()
        assert re.search(match, str(info.value), re.IGNORECASE | re.DOTALL), \
            f"error message {str(info.value)!r} does not match {match!r}"
        return info.value
    if verdict == SKIP:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            out = fn()
        messages = [str(w.message) for w in caught]
        assert any(re.search(match, m, re.IGNORECASE | re.DOTALL) for m in messages), \
            f"no warning matching {match!r}; got {messages!r}"
        return out
    return fn()
