"""bench/mutation_report.py on mutmut result files shaped like mutmut 3.8's (``mutants/<module>
.py.meta``, an ``exit_code_by_key`` map): statuses, the score, verdicts that go stale."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

from tests.bench_scripts import REPO, load_bench


@pytest.fixture(scope="module")
def report() -> ModuleType:
    return load_bench("mutation_report")


def _meta(root: Path, module: str, codes: dict[str, int | None]) -> None:
    path = root / "mutants" / f"{module}.meta"
    path.parent.mkdir(parents=True, exist_ok=True)
    # The other keys mutmut writes next to the exit codes, as it writes them.
    doc = {"exit_code_by_key": codes, "durations_by_key": {}, "estimated_durations_by_key": {}}
    path.write_text(json.dumps(doc))


@pytest.mark.parametrize(
    ("code", "word"),
    [(1, "killed"), (3, "killed"), (37, "killed"), (0, "survived"), (33, "not covered"),
     (5, "not covered"), (36, "timeout"), (-24, "timeout"), (None, "not checked"),
     (-11, "suspicious")],
)  # fmt: skip
def test_mutmut_exit_codes_map_to_their_status(
    report: ModuleType, code: int | None, word: str
) -> None:
    assert report.status(code) == word


def test_score_leaves_out_unchecked_and_accepted_mutants(
    report: ModuleType, tmp_path: Path
) -> None:
    codes = {"m.x_f__mutmut_1": 1, "m.x_f__mutmut_2": 36, "m.x_f__mutmut_3": 0,
             "m.x_f__mutmut_4": 0, "m.x_f__mutmut_5": 33, "m.x_f__mutmut_6": None}  # fmt: skip
    _meta(tmp_path, "pkg/m.py", codes)
    _meta(tmp_path, "pkg/untouched.py", {"u.x_g__mutmut_1": None})
    results = report.load_results(tmp_path)
    assert set(results) == {"pkg/m.py", "pkg/untouched.py"}
    verdicts = {
        "m.x_f__mutmut_3": {"line": "+    return a >= 0", "why": "equivalent: a is never 0"},
        "m.x_f__mutmut_4": {"line": "+    return b", "why": "written for code that moved on"},
    }
    diffs = {"m.x_f__mutmut_3": "-    return a > 0\n+    return a >= 0",
             "m.x_f__mutmut_4": "-    return c\n+    return None",
             "m.x_f__mutmut_5": "+    pass"}  # fmt: skip
    (row,) = report.summarise(results, verdicts, diffs)  # the untouched module has no row
    assert row["module"] == "pkg/m.py"
    assert (row["checked"], row["not_checked"], row["killed"], row["timeout"]) == (5, 1, 1, 1)
    assert (row["survived"], row["not_covered"], row["accepted"]) == (2, 1, 1)
    assert row["score"] == pytest.approx(2 / 4)  # (killed + timeout) / (checked - accepted)
    assert row["raw_score"] == pytest.approx(2 / 5)
    verdict = {s["mutant"]: s["verdict"] for s in row["survivors"]}
    assert verdict == {
        "m.x_f__mutmut_3": "equivalent: a is never 0",
        "m.x_f__mutmut_4": "STALE verdict",  # its line is no longer in the mutant's diff
        "m.x_f__mutmut_5": "UNEXPLAINED",
    }


def test_no_results_is_exit_status_2(
    report: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _meta(tmp_path, "pkg/m.py", {"m.x_f__mutmut_1": None})  # generated, never run
    assert report.main(["--root", str(tmp_path)]) == 2
    assert "run `make mutate` first" in capsys.readouterr().err


def test_json_report_and_goal_decide_the_exit_status(
    report: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _meta(tmp_path, "pkg/m.py", {f"m.x_f__mutmut_{i}": 1 for i in range(9)})
    out = tmp_path / "report.json"
    assert report.main(["--root", str(tmp_path), "--json", "--out", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads(out.read_text())
    assert printed["goal"] == 0.85 and printed["modules"][0]["score"] == 1.0
    # 8 of 10 killed, the other two not run by mutmut: 100 % of those checked.
    _meta(tmp_path, "pkg/m.py", {**{f"m.x_f__mutmut_{i}": 1 for i in range(8)},
                                 "m.x_f__mutmut_8": None, "m.x_f__mutmut_9": None})  # fmt: skip
    assert report.main(["--root", str(tmp_path), "--json"]) == 0


def test_an_unexplained_survivor_below_the_goal_fails_the_report(
    report: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # 5 killed, 1 survivor whose mutated file is gone (no diff, so no verdict can apply).
    _meta(tmp_path, "pkg/m.py", {**{f"m.x_f__mutmut_{i}": 1 for i in range(5)},
                                 "m.x_f__mutmut_5": 0})  # fmt: skip
    assert report.main(["--root", str(tmp_path)]) == 1  # 5/6 = 83 % < 85 %
    out = capsys.readouterr().out
    assert "m.x_f__mutmut_5 (survived): UNEXPLAINED" in out and "83.3%" in out


ORDER_TESTS = """
import json, os

def _log(name):
    with open(os.environ["ORDER_LOG"], "a") as fh:
        fh.write(name + "\\n")

def test_slow():
    _log("slow")

def test_fast():
    _log("fast")

def test_unknown():
    _log("unknown")

def test_medium():
    _log("medium")
"""

# Stands in for mutmut's state in the process it forks per mutant: the durations it measured.
FAKE_MUTMUT = """
import sys, types
durations = {"test_order.py::test_slow": 9.0, "test_order.py::test_fast": 0.1,
             "test_order.py::test_medium": 1.0}
state_module = types.ModuleType("mutmut.state")
state_module.state = lambda: types.SimpleNamespace(duration_by_test=durations)
sys.modules["mutmut.state"] = state_module
"""


@pytest.mark.parametrize(
    ("mutant", "order"),
    [("mod.x_f__mutmut_1", ["fast", "medium", "slow", "unknown"]),
     ("", ["slow", "fast", "unknown", "medium"]),  # not under mutmut: file order
     ("stats", ["slow", "fast", "unknown", "medium"])],  # mutmut measuring: file order
)  # fmt: skip
def test_under_mutmut_the_fastest_tests_run_first(
    tmp_path: Path, mutant: str, order: list[str]
) -> None:
    (tmp_path / "test_order.py").write_text(ORDER_TESTS)
    (tmp_path / "fake_mutmut.py").write_text(FAKE_MUTMUT)
    log = tmp_path / "order.log"
    env = {k: v for k, v in os.environ.items() if k not in ("CI", "SLIPSTREAM_STRICT")}
    # Only the plugins named here: the installed ones (schemathesis, hypothesis, ...) cost
    # seconds of start-up per run and play no part.
    env |= {"PYTHONPATH": f"{REPO}{os.pathsep}{tmp_path}", "ORDER_LOG": str(log),
            "MUTANT_UNDER_TEST": mutant, "PYTEST_DISABLE_PLUGIN_AUTOLOAD": "1"}  # fmt: skip
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "fake_mutmut", "-p", "tests.conftest",
         "-p", "no:cacheprovider", "-p", "no:xdist", "-q", "test_order.py"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    assert log.read_text().split() == order
