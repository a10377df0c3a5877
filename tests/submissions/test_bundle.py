"""Submission bundles: valid ones open; malformed, hostile or mismatched ones are refused
with a clear :class:`BundleError`, and nothing is ever written outside the destination."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import zipfile
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from arena.version import ENV_VERSION
from submissions.bundle import (
    MANIFEST_NAME,
    Bundle,
    BundleLimits,
    EnvSpec,
    Manifest,
    check_env,
    make_bundle,
    open_bundle,
    parse_manifest,
    read_manifest,
    unsafe_path,
)
from submissions.errors import BundleError

pytestmark = pytest.mark.filterwarnings("ignore:Duplicate name:UserWarning")  # hostile zips

ENV = EnvSpec(env_version=ENV_VERSION)
AGENT_PY = b"class Policy:\n    def reset(self, seed=None):\n        pass\n"
FUZZ = settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


def manifest_doc(**over: Any) -> dict[str, Any]:
    """A valid python-format manifest document, with ``over`` applied (None deletes a key)."""
    doc: dict[str, Any] = {
        "schema": 1,
        "name": "tester",
        "author": "Ada",
        "format": "python",
        "entry": "agent.py",
        "class_name": "Policy",
        "obs_mode": "vector",
        "action_mode": "continuous",
        "env_version": ENV_VERSION,
    }
    for key, value in over.items():
        if value is None:
            doc.pop(key, None)
        else:
            doc[key] = value
    return doc


def raw_zip(path: Path, members: list[tuple[str | zipfile.ZipInfo, bytes]]) -> Path:
    """A zip written member by member, exactly as given (no checks)."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in members:
            zf.writestr(name, data)
    return path


def good_members(**over: Any) -> list[tuple[str | zipfile.ZipInfo, bytes]]:
    return [(MANIFEST_NAME, json.dumps(manifest_doc(**over)).encode()), ("agent.py", AGENT_PY)]


def tree(root: Path) -> set[str]:
    """Every path below ``root`` (files, folders and links), relative."""
    return {p.relative_to(root).as_posix() for p in root.rglob("*")}


def assert_refused(src: Path, dest: Path, match: str, **kwargs: Any) -> None:
    """``open_bundle`` raises a one-line BundleError and writes nothing anywhere."""
    root = dest.parent
    before = tree(root)
    with pytest.raises(BundleError, match=match) as info:
        open_bundle(src, dest, env=kwargs.pop("env", ENV), **kwargs)
    assert "\n" not in str(info.value)
    assert tree(root) == before
    assert not dest.exists()


# ---- valid bundles --------------------------------------------------------------------------


def test_make_bundle_round_trips(tmp_path: Path) -> None:
    m = Manifest.from_dict(manifest_doc(env={"lidar_rays": 64, "k_opponents": 3}))
    src = make_bundle(tmp_path / "b.zip", m, {"agent.py": AGENT_PY, "lib/helper.py": b"X = 1\n"})
    bundle = open_bundle(src, tmp_path / "out", env=ENV)
    assert isinstance(bundle, Bundle)
    assert bundle.manifest == m
    assert bundle.entry_path.read_bytes() == AGENT_PY
    assert (bundle.root / "lib" / "helper.py").read_text() == "X = 1\n"
    assert read_manifest(bundle.root) == m
    assert Manifest.from_dict(m.to_dict()) == m


def test_folder_bundle_is_copied(tmp_path: Path) -> None:
    folder = tmp_path / "folder"
    (folder / "sub").mkdir(parents=True)
    (folder / MANIFEST_NAME).write_text(json.dumps(manifest_doc()))
    (folder / "agent.py").write_bytes(AGENT_PY)
    (folder / "sub" / "w.bin").write_bytes(b"\0" * 10)
    bundle = open_bundle(folder, tmp_path / "dest", env=ENV)
    assert tree(bundle.root) == {MANIFEST_NAME, "agent.py", "sub", "sub/w.bin"}
    (folder / "agent.py").write_bytes(b"changed")  # the copy does not follow the source
    assert bundle.entry_path.read_bytes() == AGENT_PY


def test_checkpoint_bundle(tmp_path: Path) -> None:
    ckpt = Path(__file__).parents[2] / "agents" / "data" / "ppo_racer.zip"
    m = Manifest(
        name="ppo_racer", author="us", format="slipstream", entry="policy.zip",
        env_version=ENV_VERSION,
    )  # fmt: skip
    bundle = open_bundle(make_bundle(tmp_path / "b.zip", m, {"policy.zip": ckpt}), tmp_path / "x")
    assert bundle.entry_path.read_bytes() == ckpt.read_bytes()
    assert bundle.manifest.class_name == "Policy"
    assert "class_name" not in bundle.manifest.to_dict()


def test_empty_existing_destination_is_used(tmp_path: Path) -> None:
    src = raw_zip(tmp_path / "b.zip", good_members())
    (tmp_path / "dest").mkdir()
    assert open_bundle(src, tmp_path / "dest", env=ENV).entry_path.exists()


# ---- the manifest ---------------------------------------------------------------------------

BAD_MANIFESTS = [
    ({"name": None}, "missing key"),
    ({"extra": 1}, "unknown key"),
    ({"schema": 2}, "schema 2 is not supported"),
    ({"schema": True}, "schema"),
    ({"name": "no spaces allowed"}, "name"),
    ({"name": "x" * 65}, "name"),
    ({"name": 7}, "name must be a string"),
    ({"author": "a" * 200}, "author is 200 characters"),
    ({"format": "pickle", "class_name": None}, "format 'pickle' is not one of"),
    ({"obs_mode": "image"}, "obs_mode"),
    ({"action_mode": "joystick"}, "action_mode"),
    ({"entry": "../agent.py"}, "climbs out"),
    ({"entry": "/etc/passwd"}, "absolute"),
    ({"entry": "C:/x.py"}, "absolute"),
    ({"entry": "a\\b.py"}, "backslash"),
    ({"entry": "agent.txt"}, r"\.py"),
    ({"entry": MANIFEST_NAME}, "manifest itself"),
    ({"class_name": "not-an-identifier"}, "class_name"),
    ({"format": "sb3", "entry": "m.zip"}, "class_name applies to the python format only"),
    ({"env": {"lidar_rays": 0}}, r"env.lidar_rays must be an integer in"),
    ({"env": {"lidar_rays": True}}, "env.lidar_rays"),
    ({"env": {"cameras": 2}}, "env key 'cameras' is unknown"),
    ({"env": [64]}, "env must be an object"),
    ({"description": "x" * 5000}, "description"),
    ({"env_version": 1}, "env_version must be a string"),
]


@pytest.mark.parametrize(("over", "match"), BAD_MANIFESTS)
def test_bad_manifest_fields(over: dict[str, Any], match: str) -> None:
    with pytest.raises(BundleError, match=match):
        Manifest.from_dict(manifest_doc(**over))


@pytest.mark.parametrize(
    ("raw", "match"),
    [
        (b"\xff\xfe", "not valid JSON"),
        (b"[1, 2]", "must be a JSON object, not list"),
        (b'{"schema": 1, "schema": 1}', "duplicate key"),
        (b'{"schema": NaN}', "NaN is not valid JSON"),
        (b"[" * 100_000 + b"]" * 100_000, "not valid JSON"),
    ],
)
def test_bad_manifest_json(raw: bytes, match: str) -> None:
    with pytest.raises(BundleError, match=match):
        parse_manifest(raw)


def test_declared_spaces_are_checked_against_the_env() -> None:
    m = Manifest.from_dict(manifest_doc(env={"lidar_rays": 32}))
    with pytest.raises(BundleError, match="declares lidar_rays=32; the env has lidar_rays=64"):
        check_env(m, ENV)
    check_env(m, EnvSpec(env_version=ENV_VERSION, lidar_rays=32))
    with pytest.raises(BundleError, match=r"made for env version '0\.0-old'"):
        check_env(Manifest.from_dict(manifest_doc(env_version="0.0-old")), ENV)
    with pytest.raises(BundleError, match="declares action_mode 'discrete'"):
        check_env(Manifest.from_dict(manifest_doc(action_mode="discrete")), ENV)


# ---- hostile archives -----------------------------------------------------------------------


def _symlink_info(name: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name)
    info.create_system = 3
    info.external_attr = (stat.S_IFLNK | 0o777) << 16
    return info


def _fifo_info(name: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name)
    info.create_system = 3
    info.external_attr = (stat.S_IFIFO | 0o644) << 16
    return info


HOSTILE = [
    ([("../evil.py", b"x")], "climbs out of the bundle"),
    ([("a/../../evil.py", b"x")], "climbs out of the bundle"),
    ([("/etc/evil", b"x")], "is absolute"),
    ([("C:/evil", b"x")], "is absolute"),
    ([("..\\evil.py", b"x")], "backslash"),
    ([("ok/./x", b"x")], "'.' path component"),
    ([("bad\x01name", b"x")], "control characters"),
    ([("/".join(["d"] * 20) + "/x", b"x")], "folders deep"),
    ([(_symlink_info("link"), b"/etc/passwd")], "symbolic link"),
    ([(_fifo_info("pipe"), b"")], "not a regular file"),
    ([("agent.py", b"again")], "duplicate entry 'agent.py'"),
    ([("AGENT.PY", b"again")], "duplicate entry"),
    ([("agent.py/x", b"x")], "both a file and a folder"),
]


@pytest.mark.parametrize(("extra", "match"), HOSTILE)
def test_hostile_members_are_refused(
    tmp_path: Path, extra: list[tuple[Any, bytes]], match: str
) -> None:
    src = raw_zip(tmp_path / "b.zip", good_members() + extra)
    assert_refused(src, tmp_path / "dest", match)


def test_encrypted_member_is_refused(tmp_path: Path) -> None:
    src = raw_zip(tmp_path / "b.zip", [*good_members(), ("secret.bin", b"x")])
    data = bytearray(src.read_bytes())
    central = data.rfind(b"PK\x01\x02")  # the last central directory record: secret.bin
    data[central + 8] |= 0x1  # general purpose flag bit 0: encrypted
    src.write_bytes(bytes(data))
    assert_refused(src, tmp_path / "dest", "'secret.bin' is encrypted")


def test_zip_bomb_by_ratio(tmp_path: Path) -> None:
    src = raw_zip(tmp_path / "b.zip", [*good_members(), ("zeros.bin", b"\0" * (4 << 20))])
    assert_refused(src, tmp_path / "dest", r"compresses \d+:1.*zip bomb")


def test_zip_bomb_by_total(tmp_path: Path) -> None:
    members = good_members() + [(f"part{i}.bin", os.urandom(40_000)) for i in range(4)]
    src = raw_zip(tmp_path / "b.zip", members)
    limits = BundleLimits(max_total_bytes=100_000)
    assert_refused(src, tmp_path / "dest", "in total, over the 100000-byte limit", limits=limits)


def test_zip_bomb_by_whole_archive_ratio(tmp_path: Path) -> None:
    # Many members, each under the per-member threshold, together expanding 1000:1.
    members = good_members() + [(f"z{i}.bin", b"\0" * 200_000) for i in range(10)]
    src = raw_zip(tmp_path / "b.zip", members)
    assert_refused(src, tmp_path / "dest", "the archive expands")


def test_size_and_count_limits(tmp_path: Path) -> None:
    src = raw_zip(tmp_path / "b.zip", [*good_members(), ("big.bin", os.urandom(5000))])
    assert_refused(
        src, tmp_path / "d1", "upload limit", limits=BundleLimits(max_archive_bytes=1000)
    )
    assert_refused(
        src, tmp_path / "d2", "limit per file", limits=BundleLimits(max_member_bytes=4000)
    )
    assert_refused(src, tmp_path / "d3", "3 entries, over the limit of 2",
                   limits=BundleLimits(max_members=2))  # fmt: skip


def test_huge_manifest(tmp_path: Path) -> None:
    huge = manifest_doc() | {"padding": os.urandom(1 << 19).hex()}  # incompressible
    src = raw_zip(tmp_path / "b.zip", [(MANIFEST_NAME, json.dumps(huge).encode())])
    assert_refused(src, tmp_path / "dest", "manifest.json is .* bytes; at most 65536")


@pytest.mark.parametrize(
    ("members", "match"),
    [
        ([("agent.py", AGENT_PY)], "no manifest.json at the bundle's root"),
        ([("sub/manifest.json", b"{}"), ("agent.py", AGENT_PY)], "no manifest.json"),
        (good_members(entry="other.py"), "entry 'other.py' is not a file in the bundle"),
        (good_members(format="slipstream", entry="agent.py", class_name=None), "not a zip"),
        ([*good_members(entry="a.py")[:1], ("a.py", b"\xff\xfe")], "not UTF-8"),
        (good_members(env_version="9.9"), "made for env version '9.9'"),
    ],
)
def test_bad_bundle_contents(tmp_path: Path, members: list[Any], match: str) -> None:
    assert_refused(raw_zip(tmp_path / "b.zip", members), tmp_path / "dest", match)


@pytest.mark.parametrize(
    "data",
    [b"", b"not a zip at all", b"PK\x03\x04" + b"\0" * 40, b"PK\x05\x06" + b"\0" * 18],
)
def test_not_a_zip(tmp_path: Path, data: bytes) -> None:
    src = tmp_path / "b.zip"
    src.write_bytes(data)
    assert_refused(src, tmp_path / "dest", "not a valid zip archive|no manifest.json")


def test_missing_source_and_busy_destination(tmp_path: Path) -> None:
    with pytest.raises(BundleError, match="no such bundle"):
        open_bundle(tmp_path / "nope.zip", tmp_path / "dest", env=ENV)
    src = raw_zip(tmp_path / "b.zip", good_members())
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "keep.txt").write_text("mine")
    with pytest.raises(BundleError, match="exists and is not an empty folder"):
        open_bundle(src, tmp_path / "busy", env=ENV)
    assert tree(tmp_path / "busy") == {"keep.txt"}


def test_folder_with_a_link_is_refused(tmp_path: Path) -> None:
    folder = tmp_path / "folder"
    folder.mkdir()
    (folder / MANIFEST_NAME).write_text(json.dumps(manifest_doc()))
    (folder / "agent.py").write_bytes(AGENT_PY)
    (folder / "key").symlink_to(Path.home())
    with pytest.raises(BundleError, match="symbolic link"):
        open_bundle(folder, tmp_path / "dest", env=ENV)
    assert not (tmp_path / "dest").exists()


def test_corrupt_member_leaves_nothing(tmp_path: Path) -> None:
    """A member whose data does not match its CRC fails mid-extraction: dest is removed."""
    src = raw_zip(tmp_path / "b.zip", [*good_members(), ("z.bin", os.urandom(3000))])
    data = bytearray(src.read_bytes())
    with zipfile.ZipFile(src) as zf:
        info = zf.getinfo("z.bin")
    data[info.header_offset + 30 + len("z.bin") + 100] ^= 0xFF  # inside z.bin's data
    src.write_bytes(bytes(data))
    assert_refused(src, tmp_path / "dest", "corrupt entry")


def test_make_bundle_refuses_unsafe_names(tmp_path: Path) -> None:
    m = Manifest.from_dict(manifest_doc())
    with pytest.raises(BundleError, match="climbs out"):
        make_bundle(tmp_path / "b.zip", m, {"agent.py": AGENT_PY, "../x": b""})
    with pytest.raises(BundleError, match="not among the files"):
        make_bundle(tmp_path / "b.zip", m, {"other.py": AGENT_PY})


# ---- fuzzing --------------------------------------------------------------------------------

JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=20),
    lambda kids: (
        st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=12), kids, max_size=4)
    ),
    max_leaves=12,
)


@FUZZ
@given(
    st.dictionaries(
        st.sampled_from([*manifest_doc(), "env", "description", "junk"]), JSON, max_size=12
    )
)
def test_fuzz_manifest_documents(doc: dict[str, Any]) -> None:
    """Any JSON document is either a valid manifest or a BundleError: never another error."""
    base = manifest_doc()
    base.update(doc)
    try:
        m = Manifest.from_dict(base)
    except BundleError:
        return
    assert Manifest.from_dict(m.to_dict()) == m


NAME_PARTS = st.sampled_from(["a", "..", ".", "", "/", "\\", "C:", "x\x00", "dir", "agent.py"])


@FUZZ
@given(names=st.lists(st.lists(NAME_PARTS, min_size=1, max_size=4).map("/".join), max_size=5))
def test_fuzz_member_names_never_escape(tmp_path_factory: Any, names: list[str]) -> None:
    """Whatever the member names, files land only inside the destination (or nothing does)."""
    work = tmp_path_factory.mktemp("fuzz")
    members = good_members() + [(n, b"data") for n in names if n]
    src = raw_zip(work / "b.zip", members)
    try:
        bundle = open_bundle(src, work / "dest", env=ENV)
    except BundleError:
        assert tree(work) == {"b.zip"}
        return
    assert tree(work) - {"b.zip"} == {"dest", *(f"dest/{p}" for p in tree(bundle.root))}
    for path in bundle.root.rglob("*"):
        assert bundle.root.resolve() in path.resolve().parents


@FUZZ
@given(data=st.data())
def test_fuzz_corrupted_archives(tmp_path_factory: Any, data: st.DataObject) -> None:
    """Flipped bytes and truncations of a valid bundle: a BundleError or a clean extraction."""
    work = tmp_path_factory.mktemp("fuzz")
    raw = bytearray(raw_zip(work / "good.zip", good_members()).read_bytes())
    for _ in range(data.draw(st.integers(1, 8))):
        pos = data.draw(st.integers(0, len(raw) - 1))
        raw[pos] = data.draw(st.integers(0, 255))
    raw = raw[: data.draw(st.integers(0, len(raw)))]
    src = work / "b.zip"
    src.write_bytes(bytes(raw))
    try:
        bundle = open_bundle(src, work / "dest", env=ENV)
    except BundleError as err:
        assert "\n" not in str(err)
        assert tree(work) == {"good.zip", "b.zip"}
        return
    assert tree(bundle.root) <= {MANIFEST_NAME, "agent.py"}


@FUZZ
@given(blob=st.binary(max_size=2000))
def test_fuzz_random_bytes(tmp_path_factory: Any, blob: bytes) -> None:
    work = tmp_path_factory.mktemp("fuzz")
    src = work / "b.zip"
    src.write_bytes(blob)
    with pytest.raises(BundleError):
        open_bundle(src, work / "dest", env=ENV)
    assert tree(work) == {"b.zip"}


def test_unsafe_path_examples() -> None:
    assert unsafe_path("a/b/c.py") is None
    for bad in ("", "/a", "a//b", "a/", "..", "a/../b", "c:x", "a\\b", "a\x7fb"):
        assert unsafe_path(bad) is not None, bad


def test_bundle_module_imports_no_simulator() -> None:
    """The leaderboard's web process validates bundles: bundle.py must stay light."""
    code = (
        "import sys; import submissions.bundle, submissions.jobs;"
        "bad = [m for m in ('pybullet', 'torch', 'viser', 'arena') if m in sys.modules];"
        "print(bad); sys.exit(1 if bad else 0)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert out.returncode == 0, out.stdout + out.stderr
