"""Env speed: env-steps/s and agent-steps/s of ``RacingEnv.step`` on one core, 2/4/8 cars.

For each car count the script

1. records ``--steps`` control steps of actions from pure-pursuit drivers (a long race, so
   cars keep driving; if the episode ends anyway it resets with the same seed and goes on);
2. resets the env with the same seed and times ``env.step`` replaying those actions, so the
   policy's cost is excluded (resets are not timed), and in turn with it, ``CHUNK`` steps
   each, raw ``pybullet.stepSimulation`` of the issue's reference world: as many
   ``racecar.urdf`` models (pybullet_data, racecar_gym's car) as cars on a plane at
   1/240 s, one call per "step". ``env/racecar`` is env steps/s over those calls/s (the
   issue's goal: at least 0.25×; f1tenth_gym reaches 0.19×); both sides share every
   stretch of machine load, so the ratio holds on a busy machine;
3. times ``Simulator.step`` alone on the same world with the same controls (physics,
   Python tyre forces and contact collection, no observations or rewards);
4. times raw ``pybullet.stepSimulation`` on the same bodies, ``substeps`` calls per control
   step (no tyre forces: the floor any pybullet env pays).

Each repeat runs 2–4 once, in that order; every figure is the best of ``--repeats``.

``--clock cpu`` times with this process's CPU time instead of the wall clock: on a machine
shared with other busy processes the wall clock mostly measures the waiting.
``--baseline-tree DIR`` also measures the env of another checkout (e.g. the revision before
a refactor, ``git worktree add /tmp/oldtree HEAD``) in a child process, alternating with
this tree's runs so that both see the same machine load; the JSON gets both and their ratio
("before/after in one run").

The ratios show where the time goes: ``env / sim`` is the cost of observations, rewards and
bookkeeping; ``sim / raw`` that of the tyre model and pybullet calls per car. Everything runs
pinned to one core (``os.sched_setaffinity``) with BLAS/OpenMP limited to one thread, lidar
on (64 rays by default), rendering off, default rates (20 Hz control, 60 Hz physics).

Usage::

    python bench/env_speed.py [--track oval] [--cars 2 4 8] [--steps 2000] [--repeats 3]
                              [--clock wall|cpu] [--json] [--out FILE] [--profile]
                              [--baseline-tree DIR]
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import math
import os
import platform
import pstats
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from arena.env import RacingEnv

THREAD_VARS = (
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
)
# The clock every figure is timed with: wall (perf_counter) or this process's CPU time
# (process_time: what a loaded, shared machine does to the process barely shows in it).
CLOCK = [time.perf_counter]
GOAL_CARS = 4  # the reference: 4 racecar.urdf
GOAL_RATIO = 0.25  # env steps/s over racecar stepSimulation calls/s
CHUNK = 100  # env steps (and as many racecar calls) per turn of the interleaved timing


@dataclass
class Row:
    """Figures for one car count (rates per second of wall-clock time, or of this process's
    CPU time with ``--clock cpu``)."""

    n_cars: int
    steps: int  # env steps timed
    agent_steps: int  # sum over those steps of the cars that acted
    env_steps_per_s: float
    agent_steps_per_s: float
    sim_steps_per_s: float  # Simulator.step (control steps)
    raw_steps_per_s: float  # control-step equivalents of raw stepSimulation
    raw_substeps_per_s: float  # stepSimulation calls per second
    env_over_sim: float  # env time per step / Simulator.step time per step
    env_over_raw: float  # env time per step / raw pybullet time per control step
    racecar_steps_per_s: float = 0.0  # stepSimulation/s of n racecar.urdf at 1/240 s
    env_over_racecar: float = 0.0  # env steps/s over racecar_steps_per_s (goal >= 0.25)


def pin_one_core() -> int | None:
    """Limit BLAS/OpenMP to one thread and pin this process to one core (returns it)."""
    for var in THREAD_VARS:
        os.environ[var] = "1"
    if not hasattr(os, "sched_setaffinity"):
        return None
    core = min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {core})
    return core


def cpu_model() -> str:
    """The CPU's model name (Linux), else what ``platform`` knows."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def make_env(track: str, n_cars: int, lidar_rays: int, steps: int) -> RacingEnv:
    """A vector-observation env with a race long enough that cars keep driving."""
    from arena import parallel_env

    return parallel_env(
        track=track,
        n_cars=n_cars,
        laps=1000,
        lidar_rays=lidar_rays,
        max_cycles=steps + 10,
        render_mode=None,
    )


def record_actions(env: RacingEnv, steps: int, seed: int) -> list[dict[str, NDArray[Any]]]:
    """``steps`` action dicts from pure-pursuit drivers (a reset with ``seed`` when done)."""
    from agents.baselines import PursuitPolicy

    policy = PursuitPolicy(env.layout, env.params)
    obs, _ = env.reset(seed=seed)
    actions: list[dict[str, NDArray[Any]]] = []
    for _ in range(steps):
        if not env.agents:
            obs, _ = env.reset(seed=seed)
        act = {agent: policy.act(obs[agent]) for agent in env.agents}  # type: ignore[arg-type]
        actions.append(act)
        obs, *_ = env.step(act)
    return actions


def replay(
    env: RacingEnv,
    actions: list[dict[str, NDArray[Any]]],
    seed: int,
    racecar: RacecarWorld | None = None,
) -> tuple[float, int, float]:
    """Seconds spent in ``env.step`` replaying ``actions``, the agent-steps taken, and the
    seconds of as many ``racecar`` calls made in turn with them, ``CHUNK`` at a time."""
    env.reset(seed=seed)
    elapsed, agent_steps, reference = 0.0, 0, 0.0
    clock = CLOCK[0]
    for k, act in enumerate(actions):
        if not env.agents:
            env.reset(seed=seed)
        t0 = clock()
        env.step(act)
        elapsed += clock() - t0
        agent_steps += len(act)
        if racecar is not None and (k + 1) % CHUNK == 0:
            reference += racecar.time(CHUNK)
    if racecar is not None and len(actions) % CHUNK:
        reference += racecar.time(len(actions) % CHUNK)
    return elapsed, agent_steps, reference


def _poses(env: RacingEnv) -> NDArray[Any]:
    """The cars' poses (n, 3); env 0.3 keeps them in ``sim_state`` (0.2: ``state``), so the
    same script can time an older checkout (``--baseline-tree``)."""
    state = getattr(env, "sim_state", None) or env.state
    return state.poses.copy()  # type: ignore[union-attr]


def time_simulator(env: RacingEnv, actions: list[dict[str, NDArray[Any]]], seed: int) -> float:
    """Seconds of ``Simulator.step`` over the recorded controls, from the same grid."""
    import numpy as np

    env.reset(seed=seed)
    sim = env.sim
    grid = _poses(env)
    controls = np.zeros((len(actions), env.n_cars, 2))
    for k, act in enumerate(actions):
        for agent, a in act.items():
            controls[k, env.agent_index[agent]] = a
    sim.reset(grid)
    clock = CLOCK[0]
    t0 = clock()
    for row in controls:
        sim.step(row[:, 0], row[:, 1])
    return clock() - t0


def time_raw(env: RacingEnv, steps: int, seed: int) -> float:
    """Seconds of ``steps × substeps`` raw ``stepSimulation`` calls on the env's world."""
    from arena.sim import pb  # pybullet, imported with its banner silenced

    env.reset(seed=seed)
    sim = env.sim
    sim.reset(_poses(env))
    client, substeps = sim.client, sim.substeps
    step = pb.stepSimulation
    clock = CLOCK[0]
    t0 = clock()
    for _ in range(steps):
        for _ in range(substeps):
            step(physicsClientId=client)
    return clock() - t0


class RacecarWorld:
    """The issue's reference: racecar_gym's car (pybullet_data's MIT racecar, with its wheel
    and steering joints), ``n_cars`` of them on a plane at 1/240 s, nothing else — the floor
    of a pybullet racing env built on that model. A fresh world per instance (cars settled on
    their wheels); :meth:`time` times raw ``stepSimulation`` calls on it."""

    def __init__(self, n_cars: int) -> None:
        import pybullet_data

        from arena.sim import pb

        self.pb = pb
        self.client = pb.connect(pb.DIRECT)
        pb.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=self.client)
        pb.setGravity(0, 0, -9.81, physicsClientId=self.client)
        pb.setTimeStep(1.0 / 240.0, physicsClientId=self.client)
        pb.loadURDF("plane.urdf", physicsClientId=self.client)
        for k in range(n_cars):
            pb.loadURDF("racecar/racecar.urdf", [0.0, 1.0 * k, 0.2], physicsClientId=self.client)
        for _ in range(50):  # let the cars settle on their wheels
            pb.stepSimulation(physicsClientId=self.client)

    def time(self, calls: int) -> float:
        """Seconds of ``calls`` raw ``stepSimulation`` calls."""
        step, client, clock = self.pb.stepSimulation, self.client, CLOCK[0]
        t0 = clock()
        for _ in range(calls):
            step(physicsClientId=client)
        return clock() - t0

    def close(self) -> None:
        """Disconnect its client."""
        self.pb.disconnect(physicsClientId=self.client)


def measure(track: str, n_cars: int, steps: int, repeats: int, lidar_rays: int, seed: int) -> Row:
    """Best-of-``repeats`` figures for one car count (each repeat: the env and the racecar
    reference in turn, then ``Simulator.step``, then raw pybullet on the env's world)."""
    env = make_env(track, n_cars, lidar_rays, steps)
    try:
        actions = record_actions(env, steps, seed)
        env_time = sim_time = raw_time = racecar_time = math.inf
        agent_steps = 0
        for _ in range(repeats):
            racecar = RacecarWorld(n_cars)
            try:
                elapsed, agent_steps, reference = replay(env, actions, seed, racecar)
            finally:
                racecar.close()
            env_time, racecar_time = min(env_time, elapsed), min(racecar_time, reference)
            sim_time = min(sim_time, time_simulator(env, actions, seed))
            raw_time = min(raw_time, time_raw(env, steps, seed))
        substeps = env.sim.substeps
    finally:
        env.close()
    return Row(
        n_cars=n_cars,
        steps=steps,
        agent_steps=agent_steps,
        env_steps_per_s=steps / env_time,
        agent_steps_per_s=agent_steps / env_time,
        sim_steps_per_s=steps / sim_time,
        raw_steps_per_s=steps / raw_time,
        raw_substeps_per_s=steps * substeps / raw_time,
        env_over_sim=env_time / sim_time,
        env_over_raw=env_time / raw_time,
        racecar_steps_per_s=steps / racecar_time,
        env_over_racecar=racecar_time / env_time,
    )


def profile(track: str, n_cars: int, steps: int, lidar_rays: int, seed: int, top: int = 25) -> str:
    """cProfile text (by internal time, then cumulative) of the env replay."""
    env = make_env(track, n_cars, lidar_rays, steps)
    try:
        actions = record_actions(env, steps, seed)
        prof = cProfile.Profile()
        prof.enable()
        replay(env, actions, seed)
        prof.disable()
    finally:
        env.close()
    out = io.StringIO()
    stats = pstats.Stats(prof, stream=out).strip_dirs()
    stats.sort_stats("tottime").print_stats(top)
    stats.sort_stats("cumulative").print_stats(top)
    return out.getvalue()


def print_table(rows: list[Row], meta: dict[str, Any]) -> None:
    """A rich table of the figures."""
    from rich.console import Console
    from rich.table import Table

    table = Table(
        title=(
            f"RacingEnv.step on one core: track {meta['track']}, {meta['lidar_rays']}-ray "
            f"lidar, {meta['control_hz']} Hz control / {meta['physics_hz']} Hz physics, "
            f"{meta['clock']} clock, best of {meta['repeats']}"
        )
    )
    for name in (
        "cars",
        "env steps/s",
        "agent steps/s",
        "Simulator.step/s",
        "raw pybullet/s",
        "env/sim",
        "env/raw",
        "env/racecar",
    ):
        table.add_column(name, justify="right")
    for r in rows:
        table.add_row(
            str(r.n_cars),
            f"{r.env_steps_per_s:,.0f}",
            f"{r.agent_steps_per_s:,.0f}",
            f"{r.sim_steps_per_s:,.0f}",
            f"{r.raw_steps_per_s:,.0f}",
            f"{r.env_over_sim:.2f}×",
            f"{r.env_over_raw:.2f}×",
            f"{r.env_over_racecar:.2f}×",
        )
    console = Console(width=max(Console().width, 100))
    console.print(table)
    substeps = meta["physics_hz"] // meta["control_hz"]
    console.print(
        f"raw pybullet/s: control steps per second of stepSimulation alone ({substeps} calls "
        "each); env/sim and env/raw: time per env step over theirs; env/racecar: env steps/s "
        f"over stepSimulation/s of as many racecar.urdf at 1/240 s, timed in turn with the env "
        f"(goal ≥ {GOAL_RATIO}×)."
    )
    if meta.get("baseline"):
        for b in meta["baseline"]["results"]:
            console.print(
                f"{b['n_cars']} cars: {b['env_steps_per_s']:,.0f} env-steps/s here "
                f"({b['env_over_racecar']:.2f}× racecar) vs "
                f"{b['baseline_env_steps_per_s']:,.0f} in {meta['baseline']['tree']} "
                f"({b['baseline_env_over_racecar']:.2f}×): ×{b['speedup']:.2f}, same run"
            )
    console.print(f"load average: {', '.join(f'{x:.2f}' for x in meta['load_average'])}")
    goal = meta["goal"]
    if goal["measured"] is None:
        console.print(f"goal: {goal['n_cars']} cars not measured")
    else:
        verdict = "met" if goal["met"] else "NOT met"
        console.print(
            f"goal env/racecar ≥ {goal['env_over_racecar']}× with {goal['n_cars']} cars: "
            f"{verdict} ({goal['measured']:.2f}×)"
        )


def measure_tree(tree: Path, args: argparse.Namespace, n_cars: int) -> dict[str, Any]:
    """One run (one repeat) for ``n_cars`` of this script on ``tree``'s packages, in a child
    (the same timing code on both sides)."""
    cmd = [
        sys.executable,
        str(Path(__file__).resolve()),  # this script, that tree's packages (PYTHONPATH)
        "--track",
        args.track,
        "--cars",
        str(n_cars),
        "--steps",
        str(args.steps),
        "--repeats",
        "1",
        "--lidar-rays",
        str(args.lidar_rays),
        "--seed",
        str(args.seed),
        "--clock",
        args.clock,
        "--json",
    ]
    env = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run(cmd, env=env, cwd=tree, capture_output=True, text=True, check=True)
    row: dict[str, Any] = json.loads(done.stdout)["results"][0]
    return row


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Measure every car count and return the JSON document."""
    CLOCK[0] = time.process_time if args.clock == "cpu" else time.perf_counter
    core = pin_one_core()
    import numpy as np

    from arena import ENV_VERSION, parallel_env
    from arena.sim import pb  # pybullet, imported with its banner silenced

    probe = parallel_env(track=args.track, n_cars=1)
    control_hz, physics_hz = probe.control_hz, probe.sim.physics_hz
    probe.close()
    baseline: dict[str, Any] | None = None
    if args.baseline_tree is None:
        rows = [
            measure(args.track, n, args.steps, args.repeats, args.lidar_rays, args.seed)
            for n in args.cars
        ]
    else:
        rows, baseline = [], {"tree": str(args.baseline_tree), "results": []}
        for n in args.cars:
            ours, theirs = [], []
            for _ in range(args.repeats):  # alternate, so both see the same machine load
                ours.append(measure(args.track, n, args.steps, 1, args.lidar_rays, args.seed))
                theirs.append(measure_tree(args.baseline_tree, args, n))
            best = max(ours, key=lambda r: r.env_steps_per_s)
            old = max(theirs, key=lambda r: r["env_steps_per_s"])
            rows.append(best)
            baseline["results"].append(
                {
                    "n_cars": n,
                    "baseline_env_steps_per_s": old["env_steps_per_s"],
                    "baseline_env_over_raw": old["env_over_raw"],
                    "baseline_env_over_racecar": old["env_over_racecar"],
                    "env_steps_per_s": best.env_steps_per_s,
                    "env_over_racecar": best.env_over_racecar,
                    "speedup": best.env_steps_per_s / old["env_steps_per_s"],
                }
            )
    at_goal = next((r for r in rows if r.n_cars == GOAL_CARS), None)
    return {
        "benchmark": "env_speed",
        "track": args.track,
        "lidar_rays": args.lidar_rays,
        "control_hz": control_hz,
        "physics_hz": physics_hz,
        "steps": args.steps,
        "repeats": args.repeats,
        "seed": args.seed,
        "env_version": ENV_VERSION,
        "pinned_core": core,
        "machine": {
            "platform": platform.platform(),
            "cpu": cpu_model(),
            "python": platform.python_version(),
            "numpy": np.__version__,
            "pybullet_api": pb.getAPIVersion(),
            "cpus": os.cpu_count(),
        },
        "clock": args.clock,
        "load_average": list(os.getloadavg()),
        "results": [asdict(r) for r in rows],
        "baseline": baseline,
        "goal": {
            "n_cars": GOAL_CARS,
            "env_over_racecar": GOAL_RATIO,
            "measured": at_goal.env_over_racecar if at_goal else None,
            "met": bool(at_goal and at_goal.env_over_racecar >= GOAL_RATIO),
        },
    }


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--track", default="oval", help="built-in track name or path")
    parser.add_argument(
        "--cars", type=int, nargs="+", default=[2, 4, 8], help="car counts to measure"
    )
    parser.add_argument("--steps", type=int, default=2000, help="control steps per run")
    parser.add_argument("--repeats", type=int, default=3, help="runs per figure (best kept)")
    parser.add_argument("--lidar-rays", type=int, default=64, help="lidar rays per car")
    parser.add_argument("--seed", type=int, default=0, help="env seed")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    parser.add_argument(
        "--clock",
        choices=["wall", "cpu"],
        default="wall",
        help="time with the wall clock or this process's CPU time (for a loaded machine)",
    )
    parser.add_argument(
        "--baseline-tree",
        type=Path,
        default=None,
        help="another checkout whose env to measure in the same run (alternating)",
    )
    parser.add_argument(
        "--profile",
        action="store_true",
        help=f"print the top of a cProfile of the {GOAL_CARS}-car run",
    )
    args = parser.parse_args(argv)
    doc = run(args)
    if args.out is not None:
        args.out.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        print_table([Row(**r) for r in doc["results"]], doc)
    if args.profile:
        text = profile(args.track, GOAL_CARS, args.steps, args.lidar_rays, args.seed)
        print(text, file=sys.stderr if args.json else sys.stdout)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
