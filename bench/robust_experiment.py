"""Nominal vs robust training arms, trained from scratch on the batched backend.

Issue 17's experiment, in one command: for every arm (``--arms``: ``nominal``, ``sample`` —
domain randomisation over :func:`arena.uncertainty.default_config` —, ``wide`` — the same
over wider intervals —, ``cvar`` — wide, each PPO update on the worst ``--cvar-share`` of
its rollout after ``--cvar-warmup`` of the budget (:mod:`agents.cvar`; in the results
``cvar@S[,wW]`` when not 0.5 and 0.2) —, ``adversarial`` — RARL, batched natures —,
``robust_mg`` — Zhang et al.'s nature over dynamics and reward; ``--curriculum R`` widens
the bounds of the domain-randomisation arms over the first R of the budget,
:mod:`agents.curriculum`, labelled ``+curR``, and ``--edge-share E`` draws their
perturbations corner-weighted, labelled ``+edgeE``; ``--natures K`` gives the nature arms a
population of K natures, labelled ``+popK``; ``--observe-perturbation`` lets the robust
arms observe their cars' perturbation, labelled ``+obs``) and every seed, ``slipstream
train --backend batch`` from scratch with the same budget (``--steps`` agent-steps), the
same tracks and ``--procedural`` share; then every policy is scored on tracks none trained
on (``--eval-tracks``: held-out built-ins and fresh generated tracks) by ``slipstream
robustness --backend batch`` over the full perturbation grid
(:data:`agents.robustness.GRID`, from ``--starts``). Per run and track: nominal score,
worst-10 % mean (CVaR₁₀) and the share of grid races not finished; per arm: the mean over
seeds of the per-track mean, with a 95 % t-interval, and for each robust arm a paired t-test
against ``nominal`` (seeds paired by index). The goal of the issue is printed beside:
worst-10 % mean ≥ 1.25 × nominal arm's with non-overlapping intervals, at ≤ 5 % loss of
nominal score; under the table, what it asks beside what any run reached (:func:`ceiling`:
the best run's worst-10 % mean, and the mean over tracks of each track's best).

Runs already trained (``<out>/<arm>_s<seed>/policy.zip``) and scored (``scores.json`` beside
it, for the same evaluation settings) are reused, so the command can be stopped and started
again, and an arm added to a finished experiment costs only its own runs; ``--runs-from``
takes the runs of earlier result files (an arm compared with arms scored before, seeds
split over processes with ``--first-seed``, or ``--seeds 0`` to summarise files together).
Usage (the issue's
budget; hours on 2 CPU cores, minutes on a GPU with ``--device cuda``)::

    python bench/robust_experiment.py --steps 20000000 --seeds 5 --out runs/robust_experiment \\
        --json bench/results/robust_experiment.json

A smoke run that checks the pipeline end to end (70 s on 2 vCPUs; every arm: a few
minutes)::

    python bench/robust_experiment.py --arms nominal cvar --steps 4096 --seeds 2 \\
        --eval-tracks random:9001 --out /tmp/robust_smoke --grid-small
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from agents.curriculum import CURRICULUM_ARMS
from agents.robustness import NATURE_ARMS

ARMS = ("nominal", "sample", "wide", "cvar", "adversarial", "robust_mg")
TRAIN_TRACKS = ("oval", "hairpins", "chicanes", "bean", "technical", "speedway")
EVAL_TRACKS = (
    "monza",
    "spielberg",
    "random:9001",
    "random:9002",
    "random:9005:length=200,difficulty=0.5,hairpin=0.7",
)
SMALL_GRID = {
    "friction": (0.6, 1.0),
    "motor": (0.8, 1.2),
    "steer_offset": (0.0,),
    "latency": (0, 2),
}


def t_interval(
    values: list[float], level: float = 0.95, bounds: tuple[float, float] | None = None
) -> dict[str, float]:
    """Mean and the two-sided t confidence interval of the mean (zero width for one value).

    ``bounds`` clips the interval to the values the quantity can take (a share: (0, 1)).
    """
    from scipy import stats

    v = np.asarray(values, dtype=np.float64)
    mean = float(v.mean())
    if len(v) < 2:
        return {"mean": mean, "lo": mean, "hi": mean, "n": len(v)}
    half = float(stats.t.ppf(0.5 + level / 2, len(v) - 1) * v.std(ddof=1) / math.sqrt(len(v)))
    lo, hi = mean - half, mean + half
    if bounds is not None:
        lo, hi = max(lo, bounds[0]), min(hi, bounds[1])
    return {"mean": mean, "lo": lo, "hi": hi, "n": len(v)}


def paired_test(robust: list[float], nominal: list[float]) -> dict[str, float]:
    """Paired t-test (robust − nominal), seeds paired by index; p two-sided."""
    from scipy import stats

    n = min(len(robust), len(nominal))
    if n < 2:
        return {"n": n, "t": float("nan"), "p": float("nan")}
    res = stats.ttest_rel(robust[:n], nominal[:n])
    return {"n": n, "t": float(res.statistic), "p": float(res.pvalue)}


def train_run(args: argparse.Namespace, arm: str, seed: int) -> Path:
    """Train one arm and seed (or reuse its checkpoint); returns the policy path."""
    from agents.train import TrainArgs, main

    run = f"{arm}_s{seed}"
    policy = args.out / run / "policy.zip"
    if policy.is_file():
        return policy
    main(
        TrainArgs(
            backend="batch",
            batch_device=args.device,
            tracks=list(args.train_tracks),
            eval_tracks=[args.train_tracks[0]],
            n_cars=args.n_cars,
            n_envs=args.n_envs,
            total_timesteps=args.steps,
            n_steps=args.n_steps,
            batch_size=args.batch_size,
            seed=seed,
            uncertainty=arm,
            procedural=args.procedural,
            procedural_length=list(args.procedural_length),
            procedural_difficulty=list(args.procedural_difficulty),
            procedural_hairpin=list(args.procedural_hairpin),
            wall_ends_episode=args.wall_ends_episode,
            n_epochs=args.n_epochs,
            eval_every=0,
            save_best=False,
            out=args.out,
            run_name=run,
            progress_bar=sys.stderr.isatty(),
            cvar_share=args.cvar_share,
            cvar_warmup=args.cvar_warmup,
            curriculum=args.curriculum if arm in CURRICULUM_ARMS else 0.0,
            edge_share=args.edge_share if arm in CURRICULUM_ARMS else 0.0,
            natures=args.natures if arm in NATURE_ARMS else 1,
            observe_perturbation=observes(args, arm),
            nature_every=max(1, args.steps // 10),
            nature_steps=max(1, args.steps // 20),
        )
    )
    return policy


def observes(args: argparse.Namespace, arm: str) -> bool:
    """``--observe-perturbation`` applies to every arm but ``nominal`` (whose cars are all
    nominal: the block would read zeros throughout)."""
    return bool(args.observe_perturbation) and arm != "nominal"


def arm_label(args: argparse.Namespace, arm: str) -> str:
    """An arm's name in the results: ``cvar`` with a share other than 0.5 is ``cvar@S``, and
    with a warm-up other than 0.2 ``cvar@S,wW``; a domain-randomisation arm trained with a
    curriculum on its bounds gets ``+curR``, one with corner-weighted draws ``+edgeE``; one
    on perturbation-aware observations ``+obs``."""
    label = arm
    if arm == "cvar" and (args.cvar_share != 0.5 or args.cvar_warmup != 0.2):
        warmup = "" if args.cvar_warmup == 0.2 else f",w{args.cvar_warmup:g}"
        label = f"cvar@{args.cvar_share:g}{warmup}"
    if args.curriculum and arm in CURRICULUM_ARMS:
        label += f"+cur{args.curriculum:g}"
    if args.edge_share and arm in CURRICULUM_ARMS:
        label += f"+edge{args.edge_share:g}"
    if args.natures > 1 and arm in NATURE_ARMS:
        label += f"+pop{args.natures}"
    if observes(args, arm):
        label += "+obs"
    return label


def score_key(args: argparse.Namespace) -> dict[str, Any]:
    """What a run's scores depend on besides its policy (a cached score must match it)."""
    return {
        "eval_tracks": list(args.eval_tracks),
        "starts": [float(s) for s in args.starts],
        "grid_small": bool(args.grid_small),
    }


def score_run(args: argparse.Namespace, policy_path: Path) -> dict[str, dict[str, float]]:
    """Per evaluation track: nominal score, worst-10 % mean and DNF share over the grid.

    The scores are kept beside the policy (``scores.json``, with :func:`score_key`) and
    reused while the policy file is older than them and the key matches: scoring 20 runs
    over the full grid takes about as long as training them.
    """
    cache = policy_path.parent / "scores.json"
    if cache.is_file() and cache.stat().st_mtime >= policy_path.stat().st_mtime:
        kept = json.loads(cache.read_text(encoding="utf-8"))
        if kept.get("key") == score_key(args):
            return dict(kept["scores"])
    scores = _score(args, policy_path)
    cache.write_text(
        json.dumps({"key": score_key(args), "scores": scores}, indent=2) + "\n", encoding="utf-8"
    )
    return scores


def _score(args: argparse.Namespace, policy_path: Path) -> dict[str, dict[str, float]]:
    """:func:`score_run` without its cache."""
    from agents.loading import load_policy
    from agents.robustness import evaluate_robustness

    policy = load_policy(str(policy_path), observe_perturbation=None)
    out = {}
    for track in args.eval_tracks:
        report = evaluate_robustness(
            policy,
            track,
            n_random=0,
            nature_steps=0,
            scales=(1.0,),
            grid=SMALL_GRID if args.grid_small else None,
            starts=tuple(args.starts),
            backend="batch",
            confirm=0,
            device=args.device,
        )
        races = [r for point in report.grid_races for r in point["races"]]
        out[track] = {
            "nominal": report.nominal,
            "worst10_mean": report.grid["worst10_mean"],
            "worst": report.grid["worst"],
            "dnf_share": float(np.mean([not r["finished"] for r in races])),
        }
    return out


def summarise_arms(runs: dict[str, dict[int, dict[str, dict[str, float]]]]) -> dict[str, Any]:
    """Per arm: t-intervals over seeds of the per-track means; paired tests against nominal."""
    per_arm: dict[str, Any] = {}
    series: dict[str, dict[str, list[float]]] = {}
    for arm, seeds in runs.items():
        ordered = [seeds[s] for s in sorted(seeds)]
        series[arm] = {
            key: [float(np.mean([t[key] for t in run.values()])) for run in ordered]
            for key in ("nominal", "worst10_mean", "worst", "dnf_share")
        }
        per_arm[arm] = {
            key: t_interval(vals, bounds=(0.0, 1.0) if key == "dnf_share" else None)
            for key, vals in series[arm].items()
        }
    if "nominal" in series:
        base = series["nominal"]
        for arm in series:
            if arm == "nominal":
                continue
            mine = per_arm[arm]
            ref = per_arm["nominal"]
            ratio = mine["worst10_mean"]["mean"] / max(ref["worst10_mean"]["mean"], 1e-9)
            loss = 1.0 - mine["nominal"]["mean"] / max(ref["nominal"]["mean"], 1e-9)
            mine["vs_nominal"] = {
                "worst10_ratio": ratio,
                "nominal_loss": loss,
                "intervals_disjoint": mine["worst10_mean"]["lo"] > ref["worst10_mean"]["hi"],
                "paired_worst10": paired_test(series[arm]["worst10_mean"], base["worst10_mean"]),
                "goal_met": bool(
                    ratio >= 1.25
                    and loss <= 0.05
                    and mine["worst10_mean"]["lo"] > ref["worst10_mean"]["hi"]
                ),
            }
    return per_arm


def ceiling(runs: dict[str, dict[int, dict[str, dict[str, float]]]]) -> dict[str, Any]:
    """What the goal asks of an arm beside what any run reached (m/s, worst-10 % means).

    ``per_track``: the best worst-10 % mean of all scored runs (every arm, every seed) on each
    evaluation track; ``envelope``: their mean — an arm's figure is the mean over tracks of
    each run's own, so a run reaches the envelope only by being the best on every track at
    once. ``best_run``: the best single run's figure (its arm and seed beside). ``goal``:
    the worst-10 % mean a robust arm needs, 1.25 × the nominal arm's, and the upper end of
    the nominal arm's interval, which the robust arm's lower end must clear (None without a
    nominal arm).
    """
    scored = [(arm, s, run) for arm, seeds in runs.items() for s, run in seeds.items()]
    if not scored:
        raise ValueError("no scored runs")
    tracks = list(scored[0][2])
    per_track = {t: max(run[t]["worst10_mean"] for _, _, run in scored) for t in tracks}
    means = [
        (float(np.mean([run[t]["worst10_mean"] for t in tracks])), a, s) for a, s, run in scored
    ]
    best, best_arm, best_seed = max(means)
    goal = None
    if "nominal" in runs:
        ref = summarise_arms({"nominal": runs["nominal"]})["nominal"]["worst10_mean"]
        goal = {"worst10_mean": 1.25 * ref["mean"], "lower_end_above": ref["hi"]}
    return {
        "per_track": per_track,
        "envelope": float(np.mean(list(per_track.values()))),
        "best_run": {"worst10_mean": best, "arm": best_arm, "seed": int(best_seed)},
        "goal": goal,
    }


def print_ceiling(figures: dict[str, Any]) -> None:
    """One line under the table: the goal's threshold beside the best runs' figures."""
    goal, best = figures["goal"], figures["best_run"]
    need = (
        f"the goal needs a worst-10 % mean ≥ {goal['worst10_mean']:.2f} m/s with its interval "
        f"above {goal['lower_end_above']:.2f}; "
        if goal
        else ""
    )
    print(
        f"{need}the best run reached {best['worst10_mean']:.2f} ({best['arm']} seed "
        f"{best['seed']}), the best on every track at once {figures['envelope']:.2f}"
    )


def print_table(summary: dict[str, Any]) -> None:
    """The per-arm figures as a rich table on stdout."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title="robustness from scratch (batch backend) · effective speed, m/s, 95 % CI")
    for col in ("arm", "nominal", "worst-10 % mean", "DNF share", "w10 / nominal arm", "paired p"):
        table.add_column(col, justify="right" if col != "arm" else "left")

    def ci(x: dict[str, float]) -> str:
        return f"{x['mean']:.2f} [{x['lo']:.2f}, {x['hi']:.2f}]"

    for arm, row in summary.items():
        vs = row.get("vs_nominal")
        table.add_row(
            arm,
            ci(row["nominal"]),
            ci(row["worst10_mean"]),
            f"{row['dnf_share']['mean']:.1%}",
            f"{vs['worst10_ratio']:.2f}" if vs else "–",
            f"{vs['paired_worst10']['p']:.3f}" if vs else "–",
        )
    Console().print(table)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Train every arm and seed (or reuse), score them, print and return the comparison."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--arms", nargs="+", default=list(ARMS), choices=ARMS)
    p.add_argument("--seeds", type=int, default=5, help="seeds per arm (1 … N)")
    p.add_argument(
        "--first-seed",
        type=int,
        default=1,
        help="train and score seeds first … first+N−1 only (split an arm over processes)",
    )
    p.add_argument(
        "--runs-from",
        type=Path,
        nargs="+",
        default=[],
        help="take the runs of these result files (the same evaluation tracks, starts and "
        "grid): every arm's seeds, merged across files, but for the seeds trained here "
        "(--seeds 0: train nothing, summarise the files together)",
    )
    p.add_argument("--steps", type=int, default=20_000_000, help="agent-steps per run (budget)")
    p.add_argument("--train-tracks", nargs="+", default=list(TRAIN_TRACKS))
    p.add_argument("--eval-tracks", nargs="+", default=list(EVAL_TRACKS))
    p.add_argument("--procedural", type=float, default=0.5, help="share of generated groups")
    p.add_argument("--procedural-length", type=float, nargs=2, default=[100.0, 250.0])
    p.add_argument("--procedural-difficulty", type=float, nargs=2, default=[0.1, 1.0])
    p.add_argument(
        "--procedural-hairpin",
        type=float,
        nargs="*",
        default=[0.45, 0.9],
        help="hairpin radius range of generated tracks (real-track tightness); none: ordinary",
    )
    p.add_argument(
        "--wall-ends-episode",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="a wall touch retires a learner car (what a wall costs on pybullet)",
    )
    p.add_argument("--n-epochs", type=int, default=5)
    p.add_argument(
        "--cvar-share", type=float, default=0.5, help="the cvar arm's share of slots per update"
    )
    p.add_argument(
        "--cvar-warmup", type=float, default=0.2, help="the cvar arm's warm-up share of the budget"
    )
    p.add_argument(
        "--curriculum",
        type=float,
        default=0.0,
        help="sample, wide and cvar arms: widen the bounds over this share of the budget "
        "(agents.curriculum; 0: off)",
    )
    p.add_argument(
        "--edge-share",
        type=float,
        default=0.0,
        help="sample, wide and cvar arms: corner-weighted draws, each parameter at an end of "
        "its interval with this probability (UncertaintyConfig.edge_share; labelled +edgeE)",
    )
    p.add_argument(
        "--natures",
        type=int,
        default=1,
        help="adversarial and robust_mg arms: a population of this many natures "
        "(agents.robustness.rarl_callback)",
    )
    p.add_argument(
        "--observe-perturbation",
        action="store_true",
        help="the robust arms observe their cars' perturbation (perturbation-aware "
        "observations, arena.uncertainty.CONTEXT_FEATURES; labelled +obs)",
    )
    p.add_argument("--n-envs", type=int, default=8, help="races per track group")
    p.add_argument("--n-cars", type=int, default=4)
    p.add_argument("--n-steps", type=int, default=64, help="PPO rollout length per slot")
    p.add_argument("--batch-size", type=int, default=4096)
    p.add_argument("--starts", type=float, nargs="+", default=[0.0, 0.5])
    p.add_argument("--grid-small", action="store_true", help="a 2×2×1×2 grid (smoke runs)")
    p.add_argument("--device", default="numpy", help="numpy, torch:cpu or cuda")
    p.add_argument("--out", type=Path, default=Path("runs/robust_experiment"))
    p.add_argument("--json", type=Path, default=None, help="write every figure here")
    p.add_argument("--plot", type=Path, default=None, help="draw the per-arm figures (PNG) here")
    p.add_argument(
        "--from-json",
        type=Path,
        default=None,
        help="train and score nothing: print (and --plot) the figures of this result file",
    )
    args = p.parse_args(argv)
    if args.from_json is not None:
        result = json.loads(args.from_json.read_text(encoding="utf-8"))
        print_table(result["arms"])
        print_ceiling(ceiling(result["runs"]))
        if args.plot is not None:
            plot_arms(result, args.plot)
        return dict(result)
    from tracks import load_track

    held = set(args.eval_tracks) & set(args.train_tracks)
    if held:
        p.error(f"evaluation tracks must be held out; also trained on: {sorted(held)}")
    for name in [*args.train_tracks, *args.eval_tracks]:
        load_track(name)
    runs: dict[str, dict[int, dict[str, dict[str, float]]]] = {}
    earlier_training: dict[str, Any] = {}
    labels = {arm_label(args, arm) for arm in args.arms}
    trained = range(args.first_seed, args.first_seed + args.seeds)
    for path in args.runs_from:
        earlier = json.loads(path.read_text(encoding="utf-8"))
        if list(earlier["eval_tracks"]) != list(args.eval_tracks):
            p.error(f"{path} was scored on other tracks: {earlier['eval_tracks']}")
        if earlier.get("budget_steps_per_run") != args.steps:  # arms compare at one budget
            p.error(
                f"{path} trained {earlier.get('budget_steps_per_run')} steps a run, "
                f"not --steps {args.steps}"
            )
        for arm, seeds in earlier["runs"].items():
            for seed, scores in seeds.items():
                if arm not in labels or int(seed) not in trained:  # this run's own win
                    if int(seed) in runs.get(arm, {}):
                        p.error(f"{path}: {arm} seed {seed} is in an earlier file too")
                    runs.setdefault(arm, {})[int(seed)] = scores
                    fig = earlier.get("training", {}).get(f"{arm}_s{seed}")
                    if fig is not None:
                        earlier_training[f"{arm}_s{seed}"] = fig
    for seed in trained:  # seed-major: a run cut short stays balanced
        for arm in args.arms:
            policy = train_run(args, arm, seed)
            runs.setdefault(arm_label(args, arm), {})[seed] = score_run(args, policy)
    summary = summarise_arms(runs)
    print_table(summary)
    limits = ceiling(runs)
    print_ceiling(limits)
    result = {
        "command": "python bench/robust_experiment.py " + " ".join(argv or sys.argv[1:]),
        "budget_steps_per_run": args.steps,
        "training": {
            **earlier_training,
            **training_figures(
                args.out,
                {a: [s for s in seeds if s in trained] for a, seeds in runs.items() if a in labels},
            ),
        },
        "train_tracks": args.train_tracks,
        "eval_tracks": args.eval_tracks,
        "runs": {arm: {str(s): v for s, v in seeds.items()} for arm, seeds in runs.items()},
        "arms": summary,
        "ceiling": limits,
    }
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    if args.plot is not None:
        plot_arms(result, args.plot)
    return result


def training_figures(out: Path, runs: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per run: the steps trained, the training wall time (s) and the machine, from its
    ``summary.json`` (runs reused from an earlier start keep their own figures)."""
    figures: dict[str, dict[str, Any]] = {}
    for arm, seeds in runs.items():
        for seed in seeds:
            path = out / f"{arm.split('@')[0]}_s{seed}" / "summary.json"  # cvar@S: cvar_sN
            if path.is_file():
                training = json.loads(path.read_text(encoding="utf-8")).get("training", {})
                figures[f"{arm}_s{seed}"] = {
                    k: training.get(k) for k in ("steps", "wall_time_s", "machine")
                }
    return figures


def plot_arms(result: dict[str, Any], path: Path) -> None:
    """Three panels (nominal score, worst-10 % mean, DNF share): every seed's mean over the
    evaluation tracks as a dot, the arm's mean with its 95 % t-interval as a bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs, arms = result["runs"], result["arms"]
    keys = (
        ("nominal", "nominal score, m/s"),
        ("worst10_mean", "worst-10 % mean, m/s"),
        ("dnf_share", "races not finished"),
    )
    fig, axes = plt.subplots(1, len(keys), figsize=(4.2 * len(keys), 3.6))
    for ax, (key, label) in zip(axes, keys, strict=True):
        for i, arm in enumerate(arms):
            seeds = [float(np.mean([t[key] for t in run.values()])) for run in runs[arm].values()]
            ax.scatter([i] * len(seeds), seeds, s=14, alpha=0.6, zorder=3)
            ci = arms[arm][key]
            ax.errorbar(
                i + 0.15,
                ci["mean"],
                yerr=[[ci["mean"] - ci["lo"]], [ci["hi"] - ci["mean"]]],
                fmt="o",
                color="black",
                capsize=4,
            )
        crowded = len(arms) > 5  # long names side by side would overlap
        ax.set_xticks(
            range(len(arms)),
            list(arms),
            rotation=30 if crowded else 0,
            ha="right" if crowded else "center",
            fontsize=8 if crowded else 10,
        )
        ax.set_title(label, fontsize=10)
        ax.grid(alpha=0.3)
    steps = result.get("budget_steps_per_run")
    fig.suptitle(
        f"held-out tracks, full perturbation grid · {steps:,} agent-steps per run · "
        "dots: seeds, bars: 95 % CI",
        fontsize=10,
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
