"""Counts the robustness rows by verdict (the ids ``error-…``, ``skip-…``, ``ok-…`` of ``verdicts.row``)."""
from collections import Counter

_COUNTS: Counter = Counter()


def pytest_runtest_logreport(report):
    if report.when != "call" or "tests/robustness/" not in report.nodeid.replace("\\", "/"):
        return
    name = report.nodeid.rsplit("[", 1)
    if len(name) != 2:
        return
    verdict = name[1].split("-", 1)[0]
    if verdict in ("error", "skip", "ok"):
        _COUNTS[(verdict, report.outcome)] += 1


def pytest_terminal_summary(terminalreporter):
    if not _COUNTS:
        return
    parts = []
    for verdict in ("error", "skip", "ok"):
        passed = _COUNTS[(verdict, "passed")]
        failed = _COUNTS[(verdict, "failed")]
        parts.append(f"{verdict}: {passed} passed" + (f", {failed} FAILED" if failed else ""))
    terminalreporter.write_line("robustness rows by verdict — " + "; ".join(parts))
