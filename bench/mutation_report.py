"""Mutation score per critical module, from a finished ``mutmut run`` (``make mutate``).

mutmut (3.x) copies the packages into ``mutants/``, plants one small bug at a time in the
modules listed under ``[tool.mutmut] only_mutate`` in pyproject.toml, and runs the tests that
cover the mutated function. A mutant is *killed* when a test fails. This script reads mutmut's
result files (``mutants/**/*.py.meta``) and prints, per module: mutants, killed, survived, not
covered, timeouts, and the score ``killed / (all − accepted)``. Every survivor is listed with
its diff and its verdict from ``bench/mutation_verdicts.json`` (why it is equivalent or
accepted). A verdict names the mutated line it was written for (``"line"``); when the code has
moved on and the mutant's diff no longer holds that line, the verdict is ``STALE`` and the
mutant counts as an unexplained survivor, like one with no verdict (``UNEXPLAINED``).

    .venv/bin/python bench/mutation_report.py [--root .] [--json out.json] [--diffs]
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


def status(code: int | None) -> str:
    """mutmut's exit code of a mutant's test run as one of our five words."""
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
    """Module path (``arena/rewards.py``) → mutant name → exit code."""
    out: dict[str, dict[str, int | None]] = {}
    for meta in sorted((root / "mutants").rglob("*.py.meta")):
        module = str(meta.relative_to(root / "mutants"))[: -len(".meta")]
        out[module] = json.loads(meta.read_text())["exit_code_by_key"]
    return out


def diff_of(root: Path, module: str, name: str) -> str:
    """The mutant's diff, as ``mutmut show`` prints it (mutmut's own function, run in ``root``)."""
    from mutmut.mutation.diff_apply import get_diff_for_mutant

    here = Path.cwd()
    try:
        os.chdir(root)
        return str(get_diff_for_mutant(name, path=module)).strip()
    finally:
        os.chdir(here)


def verdict_of(name: str, diff: str, verdicts: dict[str, dict[str, str]]) -> str | None:
    """The recorded reason a survivor is equivalent or accepted, if it still applies."""
    v = verdicts.get(name)
    if v is None:
        return None
    return v["why"] if v.get("line", "") in diff else None


def summarise(
    results: dict[str, dict[str, int | None]],
    verdicts: dict[str, dict[str, str]],
    diffs: dict[str, str],
) -> list[dict[str, Any]]:
    """One row per module: counts, score and its survivors with their verdicts."""
    rows = []
    for module, codes in results.items():
        counts = Counter(status(c) for c in codes.values())
        survivors = [n for n, c in codes.items() if status(c) in ("survived", "not covered")]
        why = {n: verdict_of(n, diffs.get(n, ""), verdicts) for n in survivors}
        accepted = [n for n in survivors if why[n] is not None]
        detected = counts["killed"] + counts["timeout"]
        considered = len(codes) - counts["not checked"] - len(accepted)
        rows.append(
            {
                "module": module,
                "mutants": len(codes),
                "killed": counts["killed"],
                "timeout": counts["timeout"],
                "survived": counts["survived"],
                "not_covered": counts["not covered"],
                "not_checked": counts["not checked"],
                "accepted": len(accepted),
                "score": detected / considered if considered else 1.0,
                "raw_score": detected / max(len(codes) - counts["not checked"], 1),
                "survivors": [
                    {
                        "mutant": n,
                        "verdict": why[n] or ("STALE verdict" if n in verdicts else "UNEXPLAINED"),
                        "diff": diffs.get(n, ""),
                    }
                    for n in survivors
                ],
            }
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    """Print the table (and the survivors); ``--json`` writes everything."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=Path("."), help="where mutants/ lies")
    parser.add_argument("--json", type=Path, help="write the report as JSON here")
    parser.add_argument("--diffs", action="store_true", help="print each survivor's diff")
    args = parser.parse_args(argv)
    results = load_results(args.root)
    if not results:
        print("no mutmut results under mutants/: run `make mutate` first", file=sys.stderr)
        return 2
    verdicts = json.loads(VERDICTS.read_text()) if VERDICTS.exists() else {}
    diffs = {
        n: diff_of(args.root, module, n)
        for module, codes in results.items()
        for n, c in codes.items()
        if status(c) in ("survived", "not covered")
    }
    rows = summarise(results, verdicts, diffs)
    table = Table(title=f"Mutation score per module (goal ≥ {GOAL:.0%})")
    for col in ("module", "mutants", "killed", "timeout", "survived", "not covered", "accepted",
                "score", "raw"):  # fmt: skip
        table.add_column(col, justify="left" if col == "module" else "right")
    for r in rows:
        table.add_row(
            r["module"], str(r["mutants"]), str(r["killed"]), str(r["timeout"]),
            str(r["survived"]), str(r["not_covered"]), str(r["accepted"]),
            f"{r['score']:.1%}", f"{r['raw_score']:.1%}",
        )  # fmt: skip
    console = Console(width=160)
    console.print(table)
    for r in rows:
        for s in r["survivors"]:
            console.print(f"[bold]{s['mutant']}[/]: {s['verdict']}", highlight=False)
            if args.diffs:
                console.print(s["diff"], highlight=False, markup=False)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0 if all(r["score"] >= GOAL for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
