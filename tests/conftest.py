"""Strict mode and the per-component count of what really ran.

Several tests need a real component of the platform that a machine may lack: the bubblewrap
namespace sandbox, the seccomp + Landlock fallback, a PostgreSQL server, Chromium, the training
extra (stable-baselines3). On a developer's machine such a test may skip; on CI it must not, or
a green run would hide that the sandbox or the database path was never exercised.

* **Strict** when ``CI`` is ``true``/``1`` (``.ci/run`` runs that way) or ``SLIPSTREAM_STRICT=1``
  (``make test STRICT=1``): every skip is turned into a failure naming what was missing.
* **Otherwise** skips stay skips, and the end of the run lists each one under a loud banner.
* **Always**: a line "real components: ..." counts the tests that passed with each component,
  found from the fixtures and parameters a test uses (``COMPONENT_FIXTURES``,
  ``COMPONENT_PARAMS``) or an explicit ``@pytest.mark.component("name")``; a component whose
  tests all skipped or failed is listed with 0.
"""

from __future__ import annotations

import math
import os
import sys
from collections import Counter
from collections.abc import Generator

import pytest

STRICT_VALUES = {"1", "true", "yes"}

# A test that uses one of these fixtures exercises the component.
COMPONENT_FIXTURES: dict[str, frozenset[str]] = {
    "postgresql": frozenset({"pg_server", "pg_url"}),
    "chromium": frozenset({"browser", "chromium_page"}),
}
# A test parametrised with (argument name, value) exercises the component.
COMPONENT_PARAMS: dict[tuple[str, str], str] = {
    ("mode", "bwrap"): "bubblewrap",
    ("mode", "seccomp"): "seccomp-fallback",
}
# A test in a module whose path holds one of these names exercises the component.
COMPONENT_MODULES: dict[str, str] = {
    "test_browser": "chromium",
    "test_train": "stable-baselines3",
}


def strict_mode() -> bool:
    """True on CI (``CI=true``) or with ``SLIPSTREAM_STRICT=1``: skips fail."""
    return any(
        os.environ.get(name, "").strip().lower() in STRICT_VALUES
        for name in ("CI", "SLIPSTREAM_STRICT")
    )


def components_of(item: pytest.Item) -> set[str]:
    """The real components a collected test exercises (see the module docstring)."""
    found = {str(m.args[0]) for m in item.iter_markers("component") if m.args}
    names = set(getattr(item, "fixturenames", ()))
    found |= {c for c, fixtures in COMPONENT_FIXTURES.items() if names & fixtures}
    callspec = getattr(item, "callspec", None)
    if callspec is not None:
        for (arg, value), component in COMPONENT_PARAMS.items():
            if str(callspec.params.get(arg, "")) == value:
                found.add(component)
    found |= {c for part, c in COMPONENT_MODULES.items() if part in item.nodeid}
    return found


def pytest_configure(config: pytest.Config) -> None:
    """Register the ``component`` marker."""
    config.addinivalue_line(
        "markers", "component(name): the test exercises a real component (counted, strict on CI)"
    )


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, pytest.TestReport, None]:
    """Tag reports with their components; in strict mode a skip becomes a failure."""
    outcome = yield
    report: pytest.TestReport = outcome.get_result()
    for component in sorted(components_of(item)):
        report.user_properties.append(("component", component))
    if report.skipped and strict_mode() and not hasattr(report, "wasxfail"):
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else report.longrepr
        report.outcome = "failed"
        report.longrepr = (
            f"STRICT (CI=true or SLIPSTREAM_STRICT=1): this test may not skip, "
            f"but it skipped: {reason}"
        )


class _Tally:
    """Counts passed tests per component and remembers skips (works across xdist workers)."""

    def __init__(self) -> None:
        self.passed: Counter[str] = Counter()
        self.seen: set[str] = set()  # components of every test reported, whatever its outcome
        self.skipped: list[tuple[str, str]] = []

    @pytest.hookimpl
    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        components = [v for k, v in report.user_properties if k == "component"]
        self.seen.update(components)
        if report.when == "call" and report.passed:
            self.passed.update(components)
        if report.skipped:
            reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else ""
            self.skipped.append((report.nodeid, str(reason)))

    @pytest.hookimpl
    def pytest_terminal_summary(self, terminalreporter: pytest.TerminalReporter) -> None:
        tr = terminalreporter
        if self.skipped:
            tr.write_sep("!", f"{len(self.skipped)} TESTS DID NOT RUN (CI would fail them)")
            for nodeid, reason in self.skipped:
                tr.write_line(f"NOT RUN {nodeid}: {reason}", yellow=True, bold=True)
        # A component whose tests all skipped or failed shows as 0: the line says what did
        # not really run, not only what did.
        counts = " · ".join(f"{name} {self.passed[name]}" for name in sorted(self.seen))
        mode = "strict" if strict_mode() else "lenient (skips allowed)"
        tr.write_line(f"real components ({mode}): {counts or 'none ran'}")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Under mutmut (``make mutate``), run the fastest tests first.

    mutmut runs the tests that called a mutated function and stops at the first failure, in
    the order it lists them (a set's); its own record of each test's duration (taken on the
    unmutated code) puts the quick ones first, so a killed mutant costs a fraction of a second
    instead of the slowest test. Outside mutmut the order is pytest's.
    """
    mutant = os.environ.get("MUTANT_UNDER_TEST", "")
    if not mutant or mutant == "stats" or "mutmut.state" not in sys.modules:
        return
    durations: dict[str, float] = sys.modules["mutmut.state"].state().duration_by_test
    items.sort(key=lambda item: durations.get(item.nodeid, math.inf))


def pytest_sessionstart(session: pytest.Session) -> None:
    """One tally per run, on the controller (it sees every worker's reports)."""
    if not hasattr(session.config, "workerinput"):
        session.config.pluginmanager.register(_Tally(), "slipstream-component-tally")
