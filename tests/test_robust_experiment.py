"""bench/robust_experiment.py's arithmetic on scored runs shaped like its result files (per
arm, per seed, per evaluation track: nominal score, worst-10 % mean, worst, DNF share): the
arm intervals, the goal check against the nominal arm, and the ceiling line printed beside."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from tests.bench_scripts import REPO, load_bench


@pytest.fixture(scope="module")
def exp() -> ModuleType:
    return load_bench("robust_experiment")


def _run(w10: dict[str, float], nominal: float = 6.0) -> dict[str, dict[str, float]]:
    return {
        t: {"nominal": nominal, "worst10_mean": v, "worst": v - 1.0, "dnf_share": 0.0}
        for t, v in w10.items()
    }


def _runs() -> dict[str, dict[int, dict[str, dict[str, float]]]]:
    # Two tracks; each robust seed is the best on one track and weak on the other, the way
    # the 20 M-step CVaR seeds are (each run's tail set by the one track it did not learn).
    return {
        "nominal": {
            1: _run({"monza": 4.0, "hairpin": 3.0}),
            2: _run({"monza": 4.2, "hairpin": 3.4}),
            3: _run({"monza": 4.4, "hairpin": 3.2}),
        },
        "cvar": {
            1: _run({"monza": 5.6, "hairpin": 4.0}, nominal=5.9),
            2: _run({"monza": 4.6, "hairpin": 5.8}, nominal=5.9),
            3: _run({"monza": 5.0, "hairpin": 5.0}, nominal=5.9),
        },
    }


def test_arms_get_t_intervals_over_seeds_and_the_goal_is_checked(exp: ModuleType) -> None:
    summary = exp.summarise_arms(_runs())
    nominal_w10 = [3.5, 3.8, 3.8]  # per seed: the mean over the tracks
    ref = summary["nominal"]["worst10_mean"]
    half = 4.302653 * np.std(nominal_w10, ddof=1) / math.sqrt(3)  # t(0.975, 2)
    assert ref["mean"] == pytest.approx(np.mean(nominal_w10))
    assert (ref["lo"], ref["hi"]) == pytest.approx((ref["mean"] - half, ref["mean"] + half))
    vs = summary["cvar"]["vs_nominal"]
    assert vs["worst10_ratio"] == pytest.approx(5.0 / np.mean(nominal_w10))  # 1.35×
    assert vs["nominal_loss"] == pytest.approx(1 - 5.9 / 6.0)
    assert vs["intervals_disjoint"] and vs["goal_met"] is True  # 1.35×, apart, 1.7 % loss
    runs = _runs()
    runs["cvar"][3] = _run({"monza": 5.0, "hairpin": 2.0}, nominal=5.9)  # one seed's blind spot
    vs = exp.summarise_arms(runs)["cvar"]["vs_nominal"]
    assert vs["worst10_ratio"] == pytest.approx(4.5 / np.mean(nominal_w10))  # still 1.22×
    assert not vs["intervals_disjoint"] and vs["goal_met"] is False
    assert vs["paired_worst10"]["n"] == 3


def test_the_ceiling_names_the_best_run_and_the_best_per_track(exp: ModuleType) -> None:
    runs = _runs()
    figures = exp.ceiling(runs)
    assert figures["per_track"] == {"monza": 5.6, "hairpin": 5.8}
    assert figures["envelope"] == pytest.approx(5.7)  # no run is best on both at once
    assert figures["best_run"] == {"worst10_mean": pytest.approx(5.2), "arm": "cvar", "seed": 2}
    ref = exp.summarise_arms({"nominal": runs["nominal"]})["nominal"]["worst10_mean"]
    assert figures["goal"] == {
        "worst10_mean": pytest.approx(1.25 * ref["mean"]),
        "lower_end_above": pytest.approx(ref["hi"]),
    }
    del runs["nominal"]
    assert exp.ceiling(runs)["goal"] is None  # a robust arm alone has nothing to clear
    with pytest.raises(ValueError, match="no scored runs"):
        exp.ceiling({})


def test_from_json_prints_the_table_and_the_ceiling(exp: ModuleType, tmp_path: Path) -> None:
    # A result file as the script writes it: seeds are strings after the JSON round trip.
    from_file = {arm: {str(s): r for s, r in seeds.items()} for arm, seeds in _runs().items()}
    result = {"runs": from_file, "arms": exp.summarise_arms(_runs())}
    path = tmp_path / "result.json"
    path.write_text(json.dumps(result))
    out = subprocess.run(
        [sys.executable, str(REPO / "bench/robust_experiment.py"), "--from-json", str(path)],
        capture_output=True,
        text=True,
        check=True,
        cwd=REPO,
    ).stdout
    assert "the best run reached 5.20 (cvar seed 2)" in out
    assert "the best on every track at once 5.70" in out
    assert "the goal needs a worst-10 % mean ≥ 4.62 m/s" in out  # 1.25 × 3.7


def test_an_edge_share_labels_the_randomising_arms_and_reaches_their_training(
    exp: ModuleType, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--edge-share E``: the domain-randomisation arms are ``+edgeE`` in the results and
    train with corner-weighted draws; nominal and the nature arms are untouched."""
    import argparse

    import agents.train

    args = argparse.Namespace(
        cvar_share=0.5, cvar_warmup=0.2, curriculum=0.0, natures=1,
        observe_perturbation=False, edge_share=0.5, out=tmp_path, device="numpy",
        train_tracks=["oval"], n_cars=2, n_envs=2, steps=4096, n_steps=32, batch_size=64,
        procedural=0.0, procedural_length=[60.0, 160.0], procedural_difficulty=[0.2, 0.8],
        procedural_hairpin=[], wall_ends_episode=True, n_epochs=1,
    )  # fmt: skip
    labels = {arm: exp.arm_label(args, arm) for arm in ("nominal", "sample", "cvar", "adversarial")}
    assert labels == {
        "nominal": "nominal", "sample": "sample+edge0.5", "cvar": "cvar+edge0.5",
        "adversarial": "adversarial",
    }  # fmt: skip
    seen: dict[str, float] = {}
    monkeypatch.setattr(
        agents.train, "main", lambda a: seen.__setitem__(a.uncertainty, a.edge_share)
    )
    for arm in ("nominal", "sample", "adversarial"):
        exp.train_run(args, arm, seed=1)
    assert seen == {"nominal": 0.0, "sample": 0.5, "adversarial": 0.0}
