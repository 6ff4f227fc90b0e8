"""The row/expect helpers themselves: a wrong verdict must fail the row."""
import warnings

import pytest

from tests.robustness.verdicts import ERROR, OK, SKIP, expect, row


def _raise():
    raise ValueError("file x.png: field 'depth' is 8-bit; expected 16-bit")


def _warn():
    warnings.warn("skipping corrupt file x.png")
    return 3


def test_error_verdict_checks_message():
    expect(_raise, ERROR, r"x\.png.*16-bit")
    with pytest.raises(AssertionError):
        expect(_raise, ERROR, "unrelated")
    with pytest.raises(pytest.fail.Exception):
        expect(lambda: 1, ERROR, "anything")


def test_skip_verdict_needs_matching_warning():
    assert expect(_warn, SKIP, r"corrupt .*x\.png") == 3
    with pytest.raises(AssertionError):
        expect(lambda: 1, SKIP, "corrupt")


def test_ok_verdict_returns_value():
    assert expect(lambda: 5, OK, None) == 5


def test_row_requires_pattern_for_error_and_skip():
    with pytest.raises(ValueError):
        row("no-pattern", 1, verdict=ERROR)
    with pytest.raises(ValueError):
        row("bad-verdict", 1, verdict="maybe")
    assert row("fine", 1, verdict=OK).id == "ok-fine"
