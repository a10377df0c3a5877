"""Mutation score per critical module, from finished ``mutmut run``\\ s (``make mutate``).

mutmut (3.x) copies the packages into ``mutants/``, plants one small bug at a time in the
modules listed under ``[tool.mutmut] only_mutate`` in pyproject.toml, and runs the tests that
called the mutated function. A mutant is *killed* when a test fails (or the tests hang past
mutmut's limit: *timeout*, also a detection). This script reads mutmut's result files
(``mutants/**/*.py.meta``) and prints, per module: the mutants checked, killed, timeouts,
survivors, not covered (no test calls the function), those accepted, and the score
``(killed + timeout) / (checked − accepted)``. Mutants ``make mutate`` does not run (outside a
module's scope, see the Makefile's ``MUTATE`` list) count as *not checked* and are left out.

Every survivor is listed with its verdict from ``bench/mutation_verdicts.json``: why it is
equivalent (no input can tell it from the original) or accepted (a difference no behaviour we
promise depends on). A verdict names the mutated line it was written for (``"line"``); when the
code has moved on and the mutant's diff no longer holds that line, the verdict is ``STALE`` and
the mutant counts as an unexplained survivor, like one with no verdict (``UNEXPLAINED``).

    .venv/bin/python bench/mutation_report.py [--root .] [--json] [--out report.json] [--diffs]

Exit status: 0 when every module reaches the goal (85 %), 1 otherwise, 2 without results.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections import Counter
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

KILLED = {1, 3, 37}  # a test failed (3: pytest internal error), or the type check caught it
SURVIVED = {0}
NOT_COVERED = {5, 33}  # no test runs the mutated function
TIMEOUT = {24, -24, 36, 152, 255}
VERDICTS = Path(__file__).with_name("mutation_verdicts.json")
GOAL = 0.85

Verdicts = dict[str, dict[str, str]]


def status(code: int | None) -> str:
    """mutmut's exit code of a mutant's test run as one of our six words."""
    if code in KILLED:
        return "killed"
    if code in SURVIVED:
        return "survived"
    if code in NOT_COVERED:
        return "not covered"
    if code in TIMEOUT:
        return "timeout"  # the mutant made the tests hang: counted as detected
    return "not checked" if code is None else "suspicious"


def load_results(root: Path) -> dict[str, dict[str, int | None]]:
    """Module path (``arena/rewards.py``) → mutant name → exit code (None: not run)."""
    out: dict[str, dict[str, int | None]] = {}
    for meta in sorted((root / "mutants").rglob("*.py.meta")):
        module = str(meta.relative_to(root / "mutants"))[: -len(".meta")]
        out[module] = json.loads(meta.read_text(encoding="utf-8"))["exit_code_by_key"]
    return out


def diff_of(root: Path, module: str, name: str) -> str:
    """The mutant's diff, as ``mutmut show`` prints it (mutmut's own function, run in ``root``);
    empty when the mutated module is gone (then no verdict can match: UNEXPLAINED)."""
    # mutmut (the dev extra) only when there is a survivor to show.
    from mutmut.mutation.diff_apply import get_diff_for_mutant

    here = Path.cwd()
    try:
        os.chdir(root)
        return str(get_diff_for_mutant(name, path=module)).strip()
    except OSError:
        return ""
    finally:
        os.chdir(here)


def verdict_of(name: str, diff: str, verdicts: Verdicts) -> str | None:
    """The recorded reason a survivor is equivalent or accepted, if it still applies.

    >>> v = {"m_1": {"line": "x >= 0", "why": "equivalent"}}
    >>> verdict_of("m_1", "-x > 0\\n+x >= 0", v), verdict_of("m_1", "+y", v)
    ('equivalent', None)
    >>> verdict_of("m_2", "+x >= 0", v) is None
    True
    """
    v = verdicts.get(name)
    if v is None:
        return None
    return v["why"] if v.get("line", "") in diff else None


def summarise(
    results: dict[str, dict[str, int | None]], verdicts: Verdicts, diffs: dict[str, str]
) -> list[dict[str, Any]]:
    """One row per module with at least one mutant checked: counts, score, survivors.

    >>> rows = summarise({"m.py": {"a": 1, "b": 0, "c": 0, "d": None}},
    ...                  {"b": {"line": "+x", "why": "equivalent"}}, {"b": "+x", "c": "+y"})
    >>> r = rows[0]
    >>> (r["checked"], r["killed"], r["survived"], r["accepted"], round(r["score"], 3))
    (3, 1, 2, 1, 0.5)
    >>> [(s["mutant"], s["verdict"]) for s in r["survivors"]]
    [('b', 'equivalent'), ('c', 'UNEXPLAINED')]
    """
    rows = []
    for module, codes in results.items():
        counts = Counter(status(c) for c in codes.values())
        checked = len(codes) - counts["not checked"]
        if not checked:
            continue
        survivors = sorted(n for n, c in codes.items() if status(c) in ("survived", "not covered"))
        why = {n: verdict_of(n, diffs.get(n, ""), verdicts) for n in survivors}
        accepted = [n for n in survivors if why[n] is not None]
        detected = counts["killed"] + counts["timeout"]
        considered = checked - len(accepted)
        rows.append(
            {
                "module": module,
                "checked": checked,
                "not_checked": counts["not checked"],
                "killed": counts["killed"],
                "timeout": counts["timeout"],
                "survived": counts["survived"],
                "not_covered": counts["not covered"],
                "suspicious": counts["suspicious"],
                "accepted": len(accepted),
                "score": detected / considered if considered else 1.0,
                "raw_score": detected / checked,
                "survivors": [
                    {
                        "mutant": n,
                        "status": status(codes[n]),
                        "verdict": why[n] or ("STALE verdict" if n in verdicts else "UNEXPLAINED"),
                        "diff": diffs.get(n, ""),
                    }
                    for n in survivors
                ],
            }
        )
    return rows


def print_report(rows: list[dict[str, Any]], *, diffs: bool) -> None:
    """The table, then each survivor with its verdict (and its diff with ``diffs``)."""
    table = Table(title=f"Mutation score per module (goal ≥ {GOAL:.0%})")
    columns = ("module", "checked", "killed", "timeout", "survived", "not covered", "accepted",
               "score", "raw", "not checked")  # fmt: skip
    for col in columns:
        table.add_column(col, justify="left" if col == "module" else "right")
    for r in rows:
        table.add_row(
            r["module"], str(r["checked"]), str(r["killed"]), str(r["timeout"]),
            str(r["survived"]), str(r["not_covered"]), str(r["accepted"]),
            f"{r['score']:.1%}", f"{r['raw_score']:.1%}", str(r["not_checked"]),
        )  # fmt: skip
    console = Console(width=160)
    console.print(table)
    for r in rows:
        for s in r["survivors"]:
            console.print(
                f"[bold]{s['mutant']}[/] ({s['status']}): {s['verdict']}", highlight=False
            )
            if diffs:
                console.print(s["diff"], highlight=False, markup=False)


def main(argv: list[str] | None = None) -> int:
    """Print the table and the survivors (or, with ``--json``, the report as JSON)."""
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--root", type=Path, default=Path("."), help="where mutants/ lies")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--out", type=Path, help="also write the JSON report to this file")
    parser.add_argument("--diffs", action="store_true", help="print each survivor's diff")
    args = parser.parse_args(argv)
    results = load_results(args.root)
    if not any(c is not None for codes in results.values() for c in codes.values()):
        print("no mutmut results under mutants/: run `make mutate` first", file=sys.stderr)
        return 2
    verdicts: Verdicts = {}
    if VERDICTS.exists():
        verdicts = json.loads(VERDICTS.read_text(encoding="utf-8"))
    diffs = {
        n: diff_of(args.root, module, n)
        for module, codes in results.items()
        for n, c in codes.items()
        if status(c) in ("survived", "not covered")
    }
    rows = summarise(results, verdicts, diffs)
    report = {"goal": GOAL, "modules": rows}
    if args.out:
        args.out.write_text(json.dumps(report, indent=2, ensure_ascii=False) + "\n")
    if args.json:
        print(json.dumps(report, indent=2, ensure_ascii=False))
    else:
        print_report(rows, diffs=args.diffs)
    return 0 if all(r["score"] >= GOAL for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
