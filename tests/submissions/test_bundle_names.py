"""Bundle names at the boundaries: a name becomes a folder (``evaluate --out``'s default) and
part of job ids and file names, so ``.``, ``..`` (issue 12: ``evaluate`` then wrote into the
output folder's parent), empty, hidden, option-like and over-long names are refused."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from submissions.bundle import MANIFEST_NAME, open_bundle
from submissions.errors import BundleError

from .test_bundle import ENV, good_members, manifest_doc, raw_zip

GOOD = ["a", "7", "A" * 64, "ppo_racer", "team-7.v2", "a..b", "x.", "a_"]
BAD = ["", ".", "..", "...", ".hidden", "-rf", "_private", "A" * 65, "a/b", "../up", "a b", "é"]


@pytest.mark.parametrize("name", GOOD)
def test_safe_names_are_accepted(tmp_path: Path, name: str) -> None:
    zipped = raw_zip(tmp_path / "b.zip", good_members(name=name))
    assert open_bundle(zipped, tmp_path / "out", env=ENV).manifest.name == name


@pytest.mark.parametrize("name", BAD)
def test_unsafe_names_are_refused_before_anything_is_written(tmp_path: Path, name: str) -> None:
    zipped = raw_zip(tmp_path / "b.zip", good_members(name=name))
    with pytest.raises(BundleError, match="name"):
        open_bundle(zipped, tmp_path / "out", env=ENV)
    assert not (tmp_path / "out").exists()


def test_a_folder_bundle_named_dot_dot_is_refused(tmp_path: Path) -> None:
    folder = tmp_path / "bundle"
    folder.mkdir()
    (folder / MANIFEST_NAME).write_text(json.dumps(manifest_doc(name="..")))
    (folder / "agent.py").write_text("class Policy:\n    pass\n")
    with pytest.raises(BundleError, match="name"):
        open_bundle(folder, tmp_path / "out", env=ENV)
