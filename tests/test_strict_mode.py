"""The strict mode of ``tests/conftest.py``: on CI a skip fails the run, locally it is listed.

Each case runs pytest in a subprocess on a throwaway test file that skips the way our real
tests do when a component is missing (``pytest.skip`` in a fixture, ``importorskip``, a
``skipif`` marker), with the project's conftest loaded as a plugin.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

SKIPPING = """
import pytest

@pytest.fixture
def pg_url():
    pytest.skip("PostgreSQL binaries not found")

def test_needs_postgres(pg_url):
    assert pg_url

def test_needs_missing_extra():
    pytest.importorskip("no_such_extra_for_slipstream")

@pytest.mark.skipif(True, reason="chromium is not installed")
def test_needs_chromium():
    pass

@pytest.mark.component("bubblewrap")
def test_really_ran():
    assert 1 + 1 == 2
"""


def run_pytest(tmp_path: Path, **env: str) -> subprocess.CompletedProcess[str]:
    """pytest on the skipping file with our conftest as a plugin and ``env`` added."""
    (tmp_path / "test_skipping.py").write_text(SKIPPING)
    clean = {k: v for k, v in os.environ.items() if k not in ("CI", "SLIPSTREAM_STRICT")}
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "tests.conftest", "-p", "no:cacheprovider",
         "-p", "no:xdist", "-q", str(tmp_path)],
        # Only the plugins named here: the installed ones cost seconds of start-up per run.
        cwd=REPO, env={**clean, **env, "PYTHONPATH": str(REPO),
                       "PYTEST_DISABLE_PLUGIN_AUTOLOAD": "1"},
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip


@pytest.mark.parametrize("env", [{"CI": "true"}, {"SLIPSTREAM_STRICT": "1"}])
def test_strict_mode_fails_every_skip(tmp_path: Path, env: dict[str, str]) -> None:
    done = run_pytest(tmp_path, **env)
    assert done.returncode == 1, done.stdout
    assert done.stdout.count("STRICT (CI=true or SLIPSTREAM_STRICT=1)") >= 3
    assert "1 passed" in done.stdout
    assert "PostgreSQL binaries not found" in done.stdout
    # The PostgreSQL test did not pass: its component is listed with 0, not left out.
    assert "real components (strict): bubblewrap 1 · postgresql 0\n" in done.stdout


def test_lenient_mode_skips_loudly(tmp_path: Path) -> None:
    done = run_pytest(tmp_path)
    assert done.returncode == 0, done.stdout
    assert "3 TESTS DID NOT RUN (CI would fail them)" in done.stdout
    assert "NOT RUN" in done.stdout and "chromium is not installed" in done.stdout
    assert "real components (lenient (skips allowed)): bubblewrap 1 · postgresql 0\n" in done.stdout
