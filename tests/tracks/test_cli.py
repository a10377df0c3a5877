"""``slipstream tracks``: list, show and import, in process and through the real script."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from leaderboard.cli import EXIT_USER_ERROR, main
from tests.tracks.builders import wavy_stadium
from tracks import list_tracks, load_track
from tracks.formats import write_f1tenth

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
LIST_FIELDS = {"name", "length_m", "min_width_m", "max_width_m", "corners", "direction"}
SCRIPT = Path(sys.executable).with_name("slipstream")


def run_main(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def assert_user_error(code: int, err: str, *needles: str) -> None:
    assert code == EXIT_USER_ERROR
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("slipstream: error: ")
    assert "Traceback" not in err
    for needle in needles:
        assert needle in lines[0]


def test_list_json(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run_main(["tracks", "list", "--json"], capsys)
    assert code == 0
    rows = json.loads(out)
    assert [r["name"] for r in rows] == list_tracks() != []
    for row in rows:
        assert row.keys() >= LIST_FIELDS
        track = load_track(row["name"])
        assert row["length_m"] == pytest.approx(track.length, abs=0.01)
        assert 0 < row["min_width_m"] <= row["max_width_m"]
        assert row["direction"] in ("ccw", "cw")
        assert row["corners"] == track.n_corners


def test_list_names_and_table(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run_main(["tracks", "list", "--names"], capsys)
    assert code == 0
    assert out.splitlines() == list_tracks()
    code, out, _ = run_main(["tracks", "list"], capsys)
    assert code == 0
    for name in list_tracks():
        assert name in out
    assert "length m" in out


def test_show_writes_a_png(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    name = list_tracks()[0]
    out_png = tmp_path / "plots" / f"{name}.png"
    code, out, _ = run_main(["tracks", "show", name, "--out", str(out_png)], capsys)
    assert code == 0
    assert out_png.read_bytes()[:8] == PNG_MAGIC
    assert out_png.stat().st_size > 20_000  # a real drawing, not an empty canvas
    assert str(out_png) in out


def test_show_a_track_file_with_json_output(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    csv = tmp_path / "wavy.csv"
    write_f1tenth(wavy_stadium(), csv)
    out_svg = tmp_path / "wavy.svg"
    code, out, _ = run_main(["tracks", "show", str(csv), "--out", str(out_svg), "--json"], capsys)
    assert code == 0
    assert json.loads(out)["out"] == str(out_svg)
    assert out_svg.read_text().lstrip().startswith("<?xml")


def test_import_f1tenth_to_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    original = wavy_stadium().reversed()
    csv = tmp_path / "in.csv"
    write_f1tenth(original, csv)
    target = tmp_path / "out" / "mine.json"
    argv = ["tracks", "import", str(csv), "--format", "f1tenth", "--name", "mine"]
    code, out, _ = run_main([*argv, "--out", str(target)], capsys)
    assert code == 0
    assert out.count("\n") == 1 and "mine" in out and str(target) in out
    back = load_track(target)
    assert back.name == "mine"
    assert back.orientation == original.orientation == "cw"
    assert abs(back.length - original.length) < 1e-3
    on = back.project(original.centre)
    assert abs(on.d).max() < 1e-3
    left, right = back.widths_at(on.s)
    assert abs(left - original.width_left).max() < 1e-3
    assert abs(right - original.width_right).max() < 1e-3

    # An existing --out is kept unless --force is given.
    before = target.read_bytes()
    code, _, err = run_main([*argv, "--out", str(target)], capsys)
    assert_user_error(code, err, "already exists", "--force")
    assert target.read_bytes() == before
    code, out, _ = run_main([*argv, "--name", "again", "--out", str(target), "--force"], capsys)
    assert code == 0
    assert load_track(target).name == "again"


def test_import_refuses_a_broken_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    csv = tmp_path / "bad.csv"
    csv.write_text("0,0,1,1\n1,0,1\n")
    target = tmp_path / "bad.json"
    code, _, err = run_main(["tracks", "import", str(csv), "--out", str(target)], capsys)
    assert_user_error(code, err, "row 2 has 3 columns")
    assert not target.exists()


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["tracks", "show", "no-such-track"], "unknown track 'no-such-track'"),
        (["tracks", "show", "missing/track.json"], "track file not found"),
        (["tracks", "import", "missing.csv", "--out", "x.json"], "track file not found"),
        (["tracks", "show", "oval", "--checkpoints", "1"], "--checkpoints"),
        (["tracks", "show", "random:abc"], "seed must be an integer"),
    ],
)
def test_user_errors_exit_2_with_one_line(
    argv: list[str],
    needle: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.chdir(tmp_path)
    code, _, err = run_main(argv, capsys)
    assert_user_error(code, err, needle)


def test_real_script(tmp_path: Path) -> None:
    assert SCRIPT.is_file(), f"console script not installed next to {sys.executable}"
    ok = subprocess.run(
        [str(SCRIPT), "tracks", "list", "--json"], capture_output=True, text=True, check=False
    )
    assert ok.returncode == 0, ok.stderr
    assert [r["name"] for r in json.loads(ok.stdout)] == list_tracks()
    bad = subprocess.run(
        [str(SCRIPT), "tracks", "show", "no-such-track", "--out", str(tmp_path / "x.png")],
        capture_output=True,
        text=True,
        check=False,
    )
    assert bad.returncode == EXIT_USER_ERROR
    assert_user_error(bad.returncode, bad.stderr, "unknown track")
    assert bad.stdout == ""


def test_import_narrows_scales_and_keeps_a_raceline(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # F1TENTH-shaped files (f1tenth_racetracks: *_centerline.csv with a constant 1.1 m
    # half-width, *_raceline.csv semicolon-separated); see tests/tracks/test_real_files.py.
    from tests.tracks.builders import hairpin_points
    from tests.tracks.test_real_files import write_f1tenth_centreline, write_raceline

    pts = hairpin_points(0.6)
    csv = write_f1tenth_centreline(tmp_path / "H_centerline.csv", pts * 2.0)
    race = write_raceline(tmp_path / "H_raceline.csv", pts * 2.0, speed=6.0)
    target = tmp_path / "h.json"
    argv = ["tracks", "import", str(csv), "--scale", "0.5", "--raceline", str(race)]
    code, out, _ = run_main([*argv, "--width", "0.9", "--out", str(target), "--json"], capsys)
    assert code == 0
    summary = json.loads(out)
    assert summary["raceline"] is True
    assert any("narrowed the left half-width" in n for n in summary["notes"])
    back = load_track(target)
    assert back.raceline is not None
    assert abs(back.raceline.points - pts).max() < 1e-5  # scaled back to the hairpin's size
    assert back.width_right.max() == pytest.approx(0.9)  # --width is in the scaled metres
    code, out, _ = run_main([*argv, "--max-width", "0.4", "--out", str(target), "--force"], capsys)
    assert code == 0 and "narrowed" not in out  # no side wider than the hairpin allows
    assert load_track(target).width.max() <= 0.8 + 1e-9
    code, _, err = run_main([*argv, "--scale", "-1", "--out", str(target), "--force"], capsys)
    assert_user_error(code, err, "--scale must be a positive number")
