"""Compare the robustness of policies trained in different ways (several seeds each).

Reads the JSON reports that ``slipstream robustness`` wrote for each run, groups them by
track and arm (the run name before ``_s<seed>``), and prints, per arm, the mean ± std and
min – max over seeds of the nominal score, the share of the full grid's races not finished
and, for every bound scale of the degradation
sweep, the grid's worst case, worst-10 % mean, mean and worst / nominal (effective speed,
m/s). ``--out`` also writes them as JSON (merged with ``--meta``, a JSON object of notes
such as the commands), ``--plot DIR`` draws one degradation PNG per track.

Usage::

    python bench/robustness_compare.py runs/robust/sweep_spielberg/*/policy_spielberg.json \
        [--out bench/results/robustness.json] [--meta notes.json] [--plot artifacts/robustness]
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import Any

import numpy as np

HEADLINE = ("nominal", "worst", "worst10_mean", "mean", "worst_over_nominal")
PER_SCALE = ("worst", "worst10_mean", "mean", "worst_over_nominal")


def arm_of(path: Path) -> tuple[str, str]:
    """(arm, run) from a report's folder name ``<arm>_s<seed>``."""
    run = path.parent.name
    match = re.fullmatch(r"(.+)_s(\d+)", run)
    return (match.group(1) if match else run), run


def spread(values: list[float]) -> dict[str, float]:
    """Mean, sample std (0 for one value), min and max, rounded to 4 places."""
    v = np.asarray(values, dtype=np.float64)
    return {
        "mean": round(float(v.mean()), 4),
        "std": round(float(v.std(ddof=1)) if len(v) > 1 else 0.0, 4),
        "min": round(float(v.min()), 4),
        "max": round(float(v.max()), 4),
    }


def run_figures(report: dict[str, Any]) -> dict[str, Any]:
    """One run's headline figures (full grid) and its degradation rows by scale."""
    grid = report["grid"]
    out: dict[str, Any] = {"nominal": round(report["nominal"], 4)}
    out.update({k: round(grid[k], 4) for k in HEADLINE[1:]})
    if report.get("random"):
        out["random_mean"] = round(report["random"]["mean"], 4)
    races = [race for point in report["grid_races"] for race in point.get("races", [point])]
    out["grid_dnf_share"] = round(float(np.mean([not race["finished"] for race in races])), 4)
    out["by_scale"] = {
        str(row["scale"]): {k: round(row[k], 4) for k in PER_SCALE} for row in report["degradation"]
    }
    return out


def compare(paths: list[Path]) -> dict[str, Any]:
    """Per track, per arm: the runs, and the spread over them of every figure."""
    tracks: dict[str, Any] = {}
    for path in sorted(paths):
        report = json.loads(path.read_text(encoding="utf-8"))
        arm, run = arm_of(path)
        arms = tracks.setdefault(report["track"], {"starts": report.get("starts", [0.0])})
        entry = arms.setdefault("arms", {}).setdefault(arm, {"runs": {}})
        entry["runs"][run] = run_figures(report)
    for track in tracks.values():
        for entry in track["arms"].values():
            runs = list(entry["runs"].values())
            entry["seeds"] = len(runs)
            keys = [k for k in runs[0] if k != "by_scale"]
            entry["stats"] = {k: spread([r[k] for r in runs]) for k in keys}
            entry["stats_by_scale"] = {
                s: {k: spread([r["by_scale"][s][k] for r in runs]) for k in PER_SCALE}
                for s in runs[0]["by_scale"]
            }
    return tracks


def plot(tracks: dict[str, Any], folder: Path) -> list[Path]:
    """Per track: worst-10 % mean and worst case against the bound scale, one line per arm
    (mean over seeds, min – max shaded). Returns the PNG paths."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for track, data in tracks.items():
        fig = Figure(figsize=(10.0, 4.0), dpi=100)
        FigureCanvasAgg(fig)
        for col, key in enumerate(("worst10_mean", "worst")):
            ax = fig.add_subplot(1, 2, col + 1)
            for arm, entry in data["arms"].items():
                rows = entry["stats_by_scale"]
                s = [float(x) for x in rows]
                mean = [rows[x][key]["mean"] for x in rows]
                line = ax.plot(s, mean, "o-", label=f"{arm} ({entry['seeds']} seeds)")[0]
                low = [rows[x][key]["min"] for x in rows]
                high = [rows[x][key]["max"] for x in rows]
                ax.fill_between(s, low, high, color=line.get_color(), alpha=0.15)
            ax.set_xlabel("bound scale s (0: nominal, 1: full grid)")
            ax.set_ylabel("effective speed, m/s")
            ax.set_ylim(bottom=0.0)
            ax.set_title(f"{track}: grid {key.replace('10_mean', '-10 % mean')}")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8, loc="lower left")
        fig.tight_layout()
        path = folder / f"degradation_{track}.png"
        fig.savefig(path)
        paths.append(path)
    return paths


def print_table(tracks: dict[str, Any]) -> None:
    """Per track and arm: nominal, then worst / worst-10 % / mean / ratio per scale."""
    for track, data in tracks.items():
        print(f"\n{track} (starts {data['starts']}) · effective speed, m/s · mean ± std [min, max]")
        for arm, entry in data["arms"].items():
            n, d = entry["stats"]["nominal"], entry["stats"]["grid_dnf_share"]
            print(
                f"  {arm} ({entry['seeds']} seeds) nominal {n['mean']:.2f} ± {n['std']:.2f} "
                f"[{n['min']:.2f}, {n['max']:.2f}]  full-grid DNF share {d['mean']:.3f} "
                f"± {d['std']:.3f}"
            )
            for s, row in entry["stats_by_scale"].items():
                cells = "  ".join(
                    f"{k} {v['mean']:.2f} ± {v['std']:.2f} [{v['min']:.2f}, {v['max']:.2f}]"
                    for k, v in row.items()
                )
                print(f"    s={s:<5} {cells}")


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("reports", type=Path, nargs="+", help="robustness report JSON files")
    parser.add_argument("--out", type=Path, default=None, help="write the comparison here")
    parser.add_argument("--meta", type=Path, default=None, help="JSON notes to put in --out")
    parser.add_argument("--plot", type=Path, default=None, help="folder for degradation PNGs")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = parser.parse_args()
    tracks = compare(args.reports)
    if args.out is not None:
        meta = json.loads(args.meta.read_text(encoding="utf-8")) if args.meta else {}
        args.out.parent.mkdir(parents=True, exist_ok=True)
        text = json.dumps({**meta, "tracks": tracks}, indent=2)
        args.out.write_text(text + "\n", encoding="utf-8")
    if args.plot is not None:
        for path in plot(tracks, args.plot):
            print(f"plot {path}")
    if args.json:
        print(json.dumps(tracks, indent=2))
    else:
        print_table(tracks)


if __name__ == "__main__":
    main()
