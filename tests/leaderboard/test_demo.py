"""``slipstream demo``: a fresh folder each run, the checkpoint bundle, and a whole short run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from leaderboard.demo import MARKER, checkpoint_bundle, fresh_dir
from leaderboard.errors import LeaderboardError


def test_fresh_dir_replaces_only_its_own_folders(tmp_path: Path) -> None:
    mine = fresh_dir(tmp_path / "demo")
    (mine / "leaderboard.db").write_bytes(b"old")
    again = fresh_dir(tmp_path / "demo")
    assert sorted(p.name for p in again.iterdir()) == [MARKER]
    foreign = tmp_path / "precious"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("keep me")
    with pytest.raises(LeaderboardError, match="not made by"):
        fresh_dir(foreign)
    assert (foreign / "thesis.tex").read_text() == "keep me"


def test_checkpoint_bundle_passes_upload_validation(tmp_path: Path) -> None:
    from leaderboard.settings import Settings
    from leaderboard.uploads import validate_bundle

    for name in ("ppo_racer", "ppo_robust"):
        manifest = validate_bundle(
            checkpoint_bundle(tmp_path / f"{name}.zip", name=name),
            Settings(data_dir=tmp_path / "data"),
        )
        assert (manifest.name, manifest.format, manifest.author) == (name, "slipstream", "house")


@pytest.mark.slow
def test_demo_runs_races_and_ranks_everyone(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from leaderboard.cli import main

    data = tmp_path / "demo"
    code = main(
        ["demo", "--races", "1", "--workers", "2", "--no-serve", "--json", "--data-dir", str(data)]
    )
    assert code == 0
    rows = json.loads(capsys.readouterr().out)
    # The five entries passed their validation races; one ranked race was rated.
    names = ["gap", "ppo_racer", "ppo_robust", "pursuit", "random"]
    assert sorted(r["name"] for r in rows) == names
    assert sum(r["races"] for r in rows) >= 2
    assert [r["rank"] for r in rows] == [1, 2, 3, 4, 5]
    replays = sorted(p.name for p in (data / "replays").glob("*.viser"))
    assert len(replays) == 6  # five validation races and one ranked race
