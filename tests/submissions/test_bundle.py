"""Submission bundles: valid ones open; malformed, hostile or mismatched ones are refused
with a clear :class:`BundleError`, and nothing is ever written outside the destination."""

from __future__ import annotations

import io
import json
import os
import stat
import subprocess
import sys
import threading
import zipfile
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import submissions.bundle as bundle_module
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


# ---- exact refusals and boundaries ----------------------------------------------------------
# Each refusal is pinned by its whole one-line message (what the CLI and the upload page show),
# and each limit at exactly its value (accepted) and one over (refused).


def refusal(fn: Any, *args: Any, **kwargs: Any) -> str:
    """The one-line message of the BundleError that ``fn(*args, **kwargs)`` raises."""
    with pytest.raises(BundleError) as info:
        fn(*args, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    return message


PATTERN = "[A-Za-z0-9][A-Za-z0-9_.-]{0,63}"
MANIFEST_REFUSALS = [
    ({"name": None, "author": None}, "missing key(s) name, author"),
    ({"zeta": 1, "alpha": 2}, "unknown key(s) 'alpha', 'zeta'"),
    ({"schema": 2}, "schema 2 is not supported (this version reads schema 1)"),
    ({"schema": True}, "schema True is not supported (this version reads schema 1)"),
    ({"schema": "1"}, "schema '1' is not supported (this version reads schema 1)"),
    ({"format": "sb3", "entry": "m.zip"}, "class_name applies to the python format only"),
    ({"env": [64]}, "env must be an object, not list"),
    ({"name": 7}, "name must be a string, not int"),
    ({"name": "a b"}, f"name 'a b' must match {PATTERN}"),
    ({"name": "x" * 65}, "name is 65 characters; at most 64"),
    ({"author": "a" * 129}, "author is 129 characters; at most 128"),
    ({"author": ["Ada"]}, "author must be a string, not list"),
    ({"author": "Ada\x1f"}, "author contains control characters"),
    ({"author": "Ada\r"}, "author contains control characters"),
    ({"description": "d" * 4097}, "description is 4097 characters; at most 4096"),
    ({"description": "line\x00"}, "description contains control characters"),
    ({"env_version": "v" * 33}, "env_version is 33 characters; at most 32"),
    ({"env_version": 1}, "env_version must be a string, not int"),
    (
        {"format": "pickle", "class_name": None},
        "format 'pickle' is not one of slipstream, sb3, torchscript, python",
    ),
    ({"obs_mode": "image"}, "obs_mode 'image' is not one of vector"),
    ({"action_mode": "joystick"}, "action_mode 'joystick' is not one of continuous, discrete"),
    ({"car": "tank"}, "car 'tank' is not one of f1tenth, deepracer"),
    ({"car": "c" * 33}, "car is 33 characters; at most 32"),
    ({"car": 1.5}, "car must be a string, not float"),
    ({"entry": "../agent.py"}, "entry '../agent.py' climbs out of the bundle ('..')"),
    ({"entry": ""}, "entry '' is empty"),
    ({"entry": "e" * 510 + ".py"}, "entry is 513 characters; at most 512"),
    ({"entry": MANIFEST_NAME}, "entry cannot be the manifest itself"),
    ({"entry": "agent.txt"}, "a python bundle's entry must be a .py file"),
    (
        {"class_name": "not-an-identifier"},
        "class_name 'not-an-identifier' must match [A-Za-z_][A-Za-z0-9_]{0,63}",
    ),
    ({"class_name": "C" * 65}, "class_name is 65 characters; at most 64"),
    (
        {"env": {"cameras": 2}},
        "env key 'cameras' is unknown (declarable: lidar_rays, k_opponents)",
    ),
    ({"env": {"lidar_rays": 0}}, "env.lidar_rays must be an integer in [1, 4096], not 0"),
    ({"env": {"lidar_rays": 4097}}, "env.lidar_rays must be an integer in [1, 4096], not 4097"),
    ({"env": {"lidar_rays": True}}, "env.lidar_rays must be an integer in [1, 4096], not True"),
    ({"env": {"lidar_rays": 64.0}}, "env.lidar_rays must be an integer in [1, 4096], not 64.0"),
    ({"env": {"k_opponents": -1}}, "env.k_opponents must be an integer in [0, 16], not -1"),
    ({"env": {"k_opponents": 17}}, "env.k_opponents must be an integer in [0, 16], not 17"),
]


@pytest.mark.parametrize(("over", "message"), MANIFEST_REFUSALS)
def test_manifest_refusals_say_exactly_what_is_wrong(over: dict[str, Any], message: str) -> None:
    """Every manifest refusal names the field, the bad value and the rule, in one line."""
    assert refusal(Manifest.from_dict, manifest_doc(**over)) == f"{MANIFEST_NAME}: {message}"


MANIFEST_EDGES = [
    {"name": "x" * 64, "author": "a" * 128, "description": "d" * 4096},
    {"author": "Ada Lovelace ~", "description": "two\tcolumns\nand lines"},  # space, tab, \n
    {"env_version": "v" * 32, "car": "deepracer"},
    {"entry": "e" * 509 + ".py"},  # 512 characters
    {"entry": "/".join(["d"] * 15) + "/a.py"},  # 16 path components
    {"class_name": "C" * 64},
    {"class_name": "_Private9"},
    {"env": {"lidar_rays": 1, "k_opponents": 0}},
    {"env": {"lidar_rays": 4096, "k_opponents": 16}},
]


@pytest.mark.parametrize("over", MANIFEST_EDGES)
def test_manifest_values_at_their_limits_are_accepted(over: dict[str, Any]) -> None:
    """Each limit is inclusive: a value exactly at it is a valid manifest, and round-trips."""
    m = Manifest.from_dict(manifest_doc(**over))
    for key, value in over.items():
        assert getattr(m, key) == value
    assert Manifest.from_dict(m.to_dict()) == m


def test_a_manifest_that_is_not_an_object_names_its_json_type() -> None:
    """``null`` is named as JSON names it, not as Python's NoneType."""
    assert refusal(Manifest.from_dict, None) == "manifest.json must be a JSON object, not null"
    assert refusal(Manifest.from_dict, "x") == "manifest.json must be a JSON object, not str"
    assert refusal(Manifest.from_dict, manifest_doc(name=None) | {"name": None}) == (
        "manifest.json: name must be a string, not null"
    )


def test_long_values_are_cut_in_messages() -> None:
    """A hostile manifest cannot flood the log: a value's repr is cut to 60 characters."""
    at_limit = "p" * 58  # repr: 60 characters, shown whole
    assert refusal(Manifest.from_dict, manifest_doc(format=at_limit, class_name=None)) == (
        f"{MANIFEST_NAME}: format '{at_limit}' is not one of slipstream, sb3, torchscript, python"
    )
    over = "p" * 59  # repr: 61 characters, cut to 59 + an ellipsis
    assert refusal(Manifest.from_dict, manifest_doc(format=over, class_name=None)) == (
        f"{MANIFEST_NAME}: format '{'p' * 58}… is not one of slipstream, sb3, torchscript, python"
    )


def test_a_manifest_built_in_python_is_checked_too() -> None:
    """``Manifest(...)`` validates like ``from_dict``: a wrong schema or env never exists."""
    base: dict[str, Any] = {"name": "t", "author": "a", "format": "sb3", "entry": "m.zip"}
    base["env_version"] = "0.3"
    m = Manifest(**base)  # the other fields' defaults make a valid manifest
    assert (m.obs_mode, m.action_mode, m.class_name, m.car, m.schema) == (
        "vector", "continuous", "Policy", "f1tenth", 1,
    )  # fmt: skip
    assert m.env == {} and m.description == ""
    assert refusal(Manifest, **base, schema=2) == "manifest.json: schema 2 is not supported"
    bad_env: Any = [("lidar_rays", 64)]
    assert refusal(Manifest, **base, env=bad_env) == "manifest.json: env must be an object"


def test_optional_keys_default_and_are_written_only_when_they_carry_something() -> None:
    """from_dict fills the documented defaults; to_dict writes back only what is not one."""
    doc = manifest_doc(class_name=None)
    m = Manifest.from_dict(doc)
    assert (m.class_name, m.description, m.car, dict(m.env)) == ("Policy", "", "f1tenth", {})
    assert m.to_dict() == manifest_doc()  # a python manifest always names its class
    sb3 = Manifest.from_dict(manifest_doc(format="sb3", entry="m.zip", class_name=None))
    assert sb3.to_dict() == manifest_doc(format="sb3", entry="m.zip", class_name=None)
    env = {"lidar_rays": 32}
    full = Manifest.from_dict(manifest_doc(env=env, description="fast", car="deepracer"))
    env["lidar_rays"] = 99  # the manifest holds its own copy
    assert full.to_dict() == manifest_doc(
        env={"lidar_rays": 32}, description="fast", car="deepracer"
    )


def test_env_mismatches_name_both_values() -> None:
    """check_env's refusals name the bundle, what it declares and what the env has."""
    m = Manifest.from_dict(manifest_doc(env_version="0.0-old"))
    assert refusal(check_env, m, ENV) == (
        f"bundle 'tester' was made for env version '0.0-old'; "
        f"this evaluation runs env version '{ENV_VERSION}'"
    )
    check_env(m, EnvSpec(env_version=ENV_VERSION, compatible_versions=("0.0-old",)))
    discrete = Manifest.from_dict(manifest_doc(action_mode="discrete"))
    assert refusal(check_env, discrete, ENV) == (
        "bundle 'tester' declares action_mode 'discrete'; this evaluation drives continuous actions"
    )
    two = EnvSpec(env_version=ENV_VERSION, action_modes=("continuous", "multi"))
    assert refusal(check_env, discrete, two).endswith("drives continuous or multi actions")
    check_env(discrete, replace_spec(action_modes=("continuous", "discrete")))
    k = Manifest.from_dict(manifest_doc(env={"lidar_rays": 64, "k_opponents": 2}))
    assert refusal(check_env, k, ENV) == (
        "bundle 'tester' declares k_opponents=2; the env has k_opponents=3"
    )
    check_env(k, replace_spec(k_opponents=2))


def replace_spec(**over: Any) -> EnvSpec:
    """The test env spec with ``over`` changed."""
    return EnvSpec(**{"env_version": ENV_VERSION} | over)


def test_the_current_env_spec_is_the_installed_env() -> None:
    """EnvSpec.current() reads arena.version: this env's version and its compatible ones."""
    from arena.version import COMPATIBLE_ENV_VERSIONS

    assert EnvSpec.current() == EnvSpec(
        env_version=ENV_VERSION, compatible_versions=COMPATIBLE_ENV_VERSIONS
    )
    assert COMPATIBLE_ENV_VERSIONS  # an older bundle's version is accepted, not only this one


@pytest.mark.parametrize(
    ("raw", "reason"),
    [
        (b'{"schema": 1, "schema": 1}', "duplicate key 'schema'"),
        (b'{"schema": NaN}', "NaN is not valid JSON"),
        (b'{"schema": -Infinity}', "-Infinity is not valid JSON"),
        (b"[" * 100_000 + b"]" * 100_000, "nested too deeply"),
        (b'{"%s": 1, "%s": 2}' % (b"k" * 200, b"k" * 200), "duplicate key '" + "k" * 105),
    ],
)
def test_manifest_json_refusals(raw: bytes, reason: str) -> None:
    """Strict JSON: duplicate keys and non-standard constants are refused; the reason is cut
    to 120 characters."""
    assert refusal(parse_manifest, raw) == f"{MANIFEST_NAME} is not valid JSON: {reason}"


def test_read_manifest_refuses_a_missing_linked_odd_or_oversized_file(tmp_path: Path) -> None:
    """read_manifest (an extracted bundle or a bundle folder) never follows a link, reads at
    most the cap, and refuses a folder or a FIFO with a BundleError (a folder used to escape
    as IsADirectoryError, a FIFO to hang the reader)."""
    raw = json.dumps(manifest_doc()).encode()
    assert refusal(read_manifest, tmp_path) == "no manifest.json in the bundle"
    (tmp_path / "real.json").write_bytes(raw)
    (tmp_path / MANIFEST_NAME).symlink_to(tmp_path / "real.json")
    assert refusal(read_manifest, tmp_path) == (
        "manifest.json: cannot be read (Too many levels of symbolic links; a link?)"
    )
    (tmp_path / MANIFEST_NAME).unlink()
    (tmp_path / MANIFEST_NAME).mkdir()
    assert refusal(read_manifest, tmp_path) == "manifest.json is not a regular file"
    (tmp_path / MANIFEST_NAME).rmdir()
    fifo = tmp_path / MANIFEST_NAME
    os.mkfifo(fifo)  # no writer: opening it must not wait for one
    outcome: list[str] = []
    reader = threading.Thread(target=lambda: outcome.append(refusal(read_manifest, tmp_path)))
    reader.start()
    reader.join(10)
    if reader.is_alive():  # blocked in open(): a writer releases it, then fail
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        reader.join()
        pytest.fail("read_manifest waited for a writer on a FIFO")
    assert outcome == ["manifest.json is not a regular file"]
    fifo.unlink()
    (tmp_path / MANIFEST_NAME).write_bytes(raw)
    exact = BundleLimits(max_manifest_bytes=len(raw))
    assert read_manifest(tmp_path, exact) == Manifest.from_dict(manifest_doc())
    assert refusal(read_manifest, tmp_path, BundleLimits(max_manifest_bytes=len(raw) - 1)) == (
        f"manifest.json holds more than its declared or allowed {len(raw) - 1} bytes"
    )
    padded = raw + b" " * (1 << 16)  # more than one 64 KiB read, still valid JSON
    (tmp_path / MANIFEST_NAME).write_bytes(padded)
    assert read_manifest(tmp_path, BundleLimits(max_manifest_bytes=len(padded))).name == "tester"


@pytest.mark.parametrize(
    ("name", "problem"),
    [
        ("", "is empty"),
        ("a" * 513, "is longer than 512 characters"),
        ("a\x1fb", "contains control characters"),
        ("a\x7fb", "contains control characters"),
        ("/\x00", "contains control characters"),
        ("/etc/passwd", "is absolute"),
        ("C:/Windows/evil.dll", "is absolute"),
        ("z:evil", "is absolute"),
        ("a\\b", "contains a backslash"),
        ("a/../b", "climbs out of the bundle ('..')"),
        ("..", "climbs out of the bundle ('..')"),
        ("a//b", "has an empty or '.' path component"),
        ("a/", "has an empty or '.' path component"),
        ("./a", "has an empty or '.' path component"),
        ("/".join(["d"] * 17), "is more than 16 folders deep"),
    ],
)
def test_unsafe_path_says_why(name: str, problem: str) -> None:
    """Each kind of unsafe member name has its own reason (the first that applies)."""
    assert unsafe_path(name) == problem


@pytest.mark.parametrize(
    "name",
    ["a" * 512, "/".join(["d"] * 16), "a b~", "é.py", "1:x", "ab:c", "...", "a..b/.c", "x/y.z"],
)
def test_plain_relative_paths_are_safe(name: str) -> None:
    """At the length and depth limits, with spaces, non-ASCII, or dots inside a name: fine."""
    assert unsafe_path(name) is None


# Names as written by evilarc (github.com/ptoomey3/evilarc, the zip-slip test-archive tool:
# "../" or "..\\" repeated --depth times, default 8, then --path) and by the Snyk zip-slip
# research archives (a long run of "../" to reach /tmp).
ZIP_SLIP_NAMES = [
    ("../" * 8 + "evil.txt", "climbs out of the bundle ('..')"),
    ("..\\" * 8 + "evil.txt", "contains a backslash"),
    ("..\\" * 8 + "WINDOWS\\System32\\evil.dll", "contains a backslash"),
    ("../" * 40 + "tmp/evil.txt", "climbs out of the bundle ('..')"),
    ("good/../../evil.sh", "climbs out of the bundle ('..')"),
    ("/tmp/evil.txt", "is absolute"),
]


@pytest.mark.parametrize(("name", "problem"), ZIP_SLIP_NAMES)
def test_zip_slip_archives_are_refused_by_name(tmp_path: Path, name: str, problem: str) -> None:
    """A zip-slip archive is refused before a byte is written, naming the member and why."""
    src = raw_zip(tmp_path / "evil.zip", [*good_members(), (name, b"#!/bin/sh\n")])
    message = refusal(open_bundle, src, tmp_path / "dest", env=ENV)
    assert message == f"evil.zip: entry {_short_repr(name)} {problem}; refusing the bundle"
    assert tree(tmp_path) == {"evil.zip"}


def _short_repr(value: str) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:59] + "…"


def _info(name: str, mode: int, system: int = 3) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name)
    info.create_system = system
    info.external_attr = mode << 16
    return info


@pytest.mark.parametrize(
    ("member", "message"),
    [
        (
            (_symlink_info("link"), b"/etc/passwd"),
            "entry 'link' is a symbolic link; links are refused",
        ),
        ((_fifo_info("pipe"), b""), "entry 'pipe' is not a regular file"),
        ((_info("dev", stat.S_IFCHR | 0o666), b""), "entry 'dev' is not a regular file"),
        ((_info("lib/", stat.S_IFDIR | 0o755), b"x"), "folder entry 'lib/' carries data"),
        ((_info("lib", stat.S_IFDIR | 0o755), b"x"), "folder entry 'lib' carries data"),
        (("/", b""), "entry '/' is empty; refusing the bundle"),
        (("../", b""), "entry '../' climbs out of the bundle ('..'); refusing the bundle"),
        (("AGENT.PY", b"again"), "duplicate entry 'AGENT.PY' (also 'agent.py')"),
        (("agent.py/x", b"x"), "'agent.py' is both a file and a folder"),
    ],
)
def test_hostile_member_refusals(tmp_path: Path, member: Any, message: str) -> None:
    """Each hostile member's refusal names the archive, the member and the rule."""
    src = raw_zip(tmp_path / "b.zip", [*good_members(), member])
    assert refusal(open_bundle, src, tmp_path / "dest", env=ENV) == f"b.zip: {message}"
    assert tree(tmp_path) == {"b.zip"}


@pytest.mark.parametrize(
    ("names", "clash"), [(["a/b/c", "a"], "a"), (["a/b/c", "a/b"], "a/b"), (["a/b", "a"], "a")]
)
def test_a_path_that_is_a_file_and_a_folder_is_refused(
    tmp_path: Path, names: list[str], clash: str
) -> None:
    """A file that is also a parent folder of another member, at any depth."""
    src = raw_zip(tmp_path / "b.zip", [*good_members(), *((n, b"x") for n in names)])
    assert refusal(open_bundle, src, tmp_path / "dest", env=ENV) == (
        f"b.zip: {clash!r} is both a file and a folder"
    )


def test_folders_and_modes_as_real_zip_tools_write_them(tmp_path: Path) -> None:
    """`zip -r` writes folder entries ("lib/", mode drwxr-xr-x) and regular files with their
    Unix mode; Windows tools (create_system 0) put DOS attributes where Unix keeps the mode.
    All of them open, deep paths need no folder entries, and stored members are fine."""
    stored = zipfile.ZipInfo("lib/stored.bin")
    stored.compress_type = zipfile.ZIP_STORED
    members = [
        *good_members(),
        (_info("lib/", stat.S_IFDIR | 0o755), b""),
        (_info("lib/a.py", stat.S_IFREG | 0o644), b"A = 1\n"),
        (_info("win.txt", 0o040000 | 0x20, system=0), b"dos attributes"),  # archive bit
        (_info("deep/er/still/b.py", stat.S_IFREG | 0o600), b"B = 2\n"),
        ("deep/er/still/c.py", b"C = 3\n"),
        (stored, b"\x00" * 100),
    ]
    bundle = open_bundle(raw_zip(tmp_path / "b.zip", members), tmp_path / "dest", env=ENV)
    assert tree(bundle.root) == {
        MANIFEST_NAME, "agent.py", "lib", "lib/a.py", "lib/stored.bin", "win.txt", "deep",
        "deep/er", "deep/er/still", "deep/er/still/b.py", "deep/er/still/c.py",
    }  # fmt: skip
    assert (bundle.root / "deep/er/still/c.py").read_bytes() == b"C = 3\n"
    umask = os.umask(0)
    os.umask(umask)
    for path in (bundle.entry_path, bundle.root / "deep/er/still/b.py"):
        assert stat.S_IMODE(path.stat().st_mode) == 0o644 & ~umask  # never the member's mode


def test_only_stored_and_deflated_members_are_accepted(tmp_path: Path) -> None:
    """bzip2 and lzma members are refused (their decompressors are further attack surface)."""
    for method in (zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA):
        src = tmp_path / f"{method}.zip"
        with zipfile.ZipFile(src, "w") as zf:
            for name, data in good_members():
                zf.writestr(name, data)
            zf.writestr("w.bin", b"w" * 100, compress_type=method)
        assert refusal(open_bundle, src, tmp_path / "dest", env=ENV) == (
            f"{src.name}: entry 'w.bin' uses compression method {method}; only stored and "
            "deflated entries are accepted"
        )


def test_archive_size_and_member_count_limits_are_inclusive(tmp_path: Path) -> None:
    """The upload cap and the entry count cap: exactly at them opens, one over is refused."""
    src = raw_zip(tmp_path / "b.zip", [*good_members(), ("lib/", b""), ("lib/x.py", b"x")])
    size = src.stat().st_size
    assert (
        refusal(open_bundle, src, tmp_path / "d1", BundleLimits(max_archive_bytes=size - 1), ENV)
        == f"b.zip: {size} bytes, over the {size - 1}-byte upload limit"
    )
    open_bundle(src, tmp_path / "d2", BundleLimits(max_archive_bytes=size), ENV)
    assert refusal(open_bundle, src, tmp_path / "d3", BundleLimits(max_members=3), ENV) == (
        "b.zip: 4 entries, over the limit of 3"  # the folder entry counts
    )
    open_bundle(src, tmp_path / "d4", BundleLimits(max_members=4), ENV)


def test_uncompressed_size_limits_are_inclusive(tmp_path: Path) -> None:
    """Per member and in total, exactly at the limit opens; one byte over is refused."""
    members = [*good_members(), ("big.bin", os.urandom(5000))]
    src = raw_zip(tmp_path / "b.zip", members)
    total = sum(len(data) for _, data in members)
    at = BundleLimits(max_member_bytes=5000, max_total_bytes=total)
    open_bundle(src, tmp_path / "ok", at, ENV)
    assert refusal(open_bundle, src, tmp_path / "d1", BundleLimits(max_member_bytes=4999), ENV) == (
        "b.zip: big.bin is 5000 bytes uncompressed, over the 4999-byte limit per file"
    )
    assert refusal(
        open_bundle, src, tmp_path / "d2", BundleLimits(max_total_bytes=total - 1), ENV
    ) == (
        f"b.zip: {total} bytes uncompressed in total, over the {total - 1}-byte limit (a zip bomb?)"
    )


def test_compression_ratio_limits(tmp_path: Path) -> None:
    """A member (and the whole archive) may expand exactly max_ratio:1, not more; members and
    archives up to ratio_min_bytes are not held to it at all."""
    src = tmp_path / "stored.zip"
    with zipfile.ZipFile(src, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, data in [*good_members(), ("s.bin", b"s" * 3000)]:
            zf.writestr(name, data)
    # Stored members expand exactly 1:1: at a 1:1 limit they pass, above ratio_min_bytes.
    open_bundle(src, tmp_path / "d0", BundleLimits(max_ratio=1.0, ratio_min_bytes=0), ENV)
    over = BundleLimits(max_ratio=0.99, ratio_min_bytes=2999)
    assert refusal(open_bundle, src, tmp_path / "d1", over, ENV) == (
        "stored.zip: entry 's.bin' compresses 1:1, over the 1:1 limit (a zip bomb?)"
    )
    zeros = raw_zip(tmp_path / "z.zip", [*good_members(), ("z.bin", b"\0" * 100_000)])
    with zipfile.ZipFile(zeros) as zf:
        z = zf.getinfo("z.bin")
        packed = sum(i.compress_size for i in zf.infolist())
    ratio = z.file_size / z.compress_size
    total = z.file_size + sum(len(d) for _, d in good_members())
    assert ratio > total / packed > 100
    member = BundleLimits(max_ratio=50, ratio_min_bytes=0)
    assert refusal(open_bundle, zeros, tmp_path / "d2", member, ENV) == (
        f"z.zip: entry 'z.bin' compresses {ratio:.0f}:1, over the 50:1 limit (a zip bomb?)"
    )
    # the member exactly at ratio_min_bytes is not held to the ratio; the archive is
    whole = BundleLimits(max_ratio=50, ratio_min_bytes=100_000)
    assert refusal(open_bundle, zeros, tmp_path / "d3", whole, ENV) == (
        f"z.zip: the archive expands {total / packed:.0f}:1, over the 50:1 limit (a zip bomb?)"
    )
    open_bundle(zeros, tmp_path / "d4", BundleLimits(max_ratio=50, ratio_min_bytes=total), ENV)
    at_member = BundleLimits(max_ratio=ratio, ratio_min_bytes=0)
    assert "the archive expands" not in str(_try_open(zeros, tmp_path / "d5", at_member))
    open_bundle(zeros, tmp_path / "d6", BundleLimits(max_ratio=ratio, ratio_min_bytes=0), ENV)


def _try_open(src: Path, dest: Path, limits: BundleLimits) -> Bundle | BundleError:
    try:
        return open_bundle(src, dest, limits, ENV)
    except BundleError as err:
        return err


def test_a_header_claiming_zero_compressed_bytes_is_a_bomb(tmp_path: Path) -> None:
    """A zip bomb's central directory may claim 0 compressed bytes for a huge member: the
    ratio is then taken over 1 byte (no division by zero, no pass)."""
    src = raw_zip(tmp_path / "b.zip", [*good_members(), ("lie.bin", b"x" * 10)])
    data = bytearray(src.read_bytes())
    central = data.rfind(b"PK\x01\x02")  # lie.bin's central directory record
    data[central + 20 : central + 28] = (0).to_bytes(4, "little") + (2 << 20).to_bytes(4, "little")
    src.write_bytes(bytes(data))
    assert refusal(open_bundle, src, tmp_path / "dest", env=ENV) == (
        f"b.zip: entry 'lie.bin' compresses {2 << 20}:1, over the 100:1 limit (a zip bomb?)"
    )


def folder_bundle(root: Path, extra: dict[str, bytes] | None = None) -> Path:
    """A valid bundle folder (manifest + agent.py) plus ``extra`` files (path -> bytes)."""
    root.mkdir()
    (root / MANIFEST_NAME).write_text(json.dumps(manifest_doc()))
    (root / "agent.py").write_bytes(AGENT_PY)
    for name, data in (extra or {}).items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(data)
    return root


def test_folder_bundle_limits_are_inclusive(tmp_path: Path) -> None:
    """A folder's entries (folders included), its bytes in total and per file: exactly at
    each limit it is copied, one over is refused naming the folder."""
    src = folder_bundle(tmp_path / "folder", {"sub/w.bin": b"w" * 1000})
    total = sum(p.stat().st_size for p in src.rglob("*") if p.is_file())
    open_bundle(src, tmp_path / "d0", BundleLimits(max_members=4, max_archive_bytes=total), ENV)
    assert refusal(open_bundle, src, tmp_path / "d1", BundleLimits(max_members=3), ENV) == (
        "folder: more than 3 entries"
    )
    assert (
        refusal(open_bundle, src, tmp_path / "d2", BundleLimits(max_archive_bytes=total - 1), ENV)
        == f"folder: {total} bytes of files, over the {total - 1}-byte limit"
    )
    assert refusal(open_bundle, src, tmp_path / "d3", BundleLimits(max_member_bytes=999), ENV) == (
        "folder: sub/w.bin is 1000 bytes uncompressed, over the 999-byte limit per file"
    )
    assert tree(tmp_path / "d0") == {MANIFEST_NAME, "agent.py", "sub", "sub/w.bin"}
    assert not any((tmp_path / d).exists() for d in ("d1", "d2", "d3"))


HOSTILE_FOLDER = [
    (lambda f: (f / "key").symlink_to(Path.home()), "key is a symbolic link; links are refused"),
    (lambda f: (f / "lib").symlink_to(f), "lib is a symbolic link; links are refused"),
    (lambda f: os.mkfifo(f / "pipe"), "pipe is not a regular file"),
    (lambda f: (f / "a\\b.py").write_text("x"), "entry 'a\\\\b.py' contains a backslash"),
    (lambda f: (f / "bad\x01").write_text("x"), "entry 'bad\\x01' contains control characters"),
]


@pytest.mark.parametrize(("make", "message"), HOSTILE_FOLDER)
def test_hostile_folder_entries_are_refused(tmp_path: Path, make: Any, message: str) -> None:
    """A bundle folder (``evaluate`` on a checkout) with a link, a FIFO or an unsafe name:
    refused with its relative path, nothing copied, and no link followed."""
    src = folder_bundle(tmp_path / "folder")
    make(src)
    assert refusal(open_bundle, src, tmp_path / "dest", env=ENV) == f"folder: {message}"
    assert not (tmp_path / "dest").exists()


@pytest.mark.parametrize(
    ("members", "message"),
    [
        ([("agent.py", AGENT_PY)], "b.zip: no manifest.json at the bundle's root"),
        (
            good_members(entry="other.py"),
            "the manifest's entry 'other.py' is not a file in the bundle "
            "(files: agent.py, manifest.json)",
        ),
        (
            [*good_members(entry="z.py"), *((f"f{i}.py", b"") for i in range(9))],
            "the manifest's entry 'z.py' is not a file in the bundle "
            "(files: agent.py, f0.py, f1.py, f2.py, f3.py, f4.py, f5.py, f6.py)",
        ),
        (
            good_members(format="slipstream", entry="agent.py", class_name=None),
            "entry 'agent.py' is not a zip archive, as a slipstream policy file must be",
        ),
        (
            [*good_members(format="sb3", entry="m.zip", class_name=None), ("m.zip", b"PK")],
            "entry 'm.zip' is not a zip archive, as a sb3 policy file must be",
        ),
        (
            [*good_members(format="torchscript", entry="m.pt", class_name=None),
             ("m.pt", b"PK\x05\x06" + b"\0" * 18)],
            "entry 'm.pt' is not a zip archive, as a torchscript policy file must be",
        ),
        (
            [*good_members(entry="a.py")[:1], ("a.py", b"# " + b"x" * 70_000 + b"\xff\n")],
            "entry 'a.py' is not UTF-8 Python source",  # past the first 64 KiB read
        ),
    ],
)  # fmt: skip
def test_bad_bundle_contents_exact(tmp_path: Path, members: list[Any], message: str) -> None:
    """The manifest must be at the root and its entry must exist and look like its format
    (a zip archive for checkpoints, UTF-8 throughout for Python source)."""
    src = raw_zip(tmp_path / "b.zip", members)
    assert refusal(open_bundle, src, tmp_path / "dest", env=ENV) == message
    assert tree(tmp_path) == {"b.zip"}


def test_a_zip_entry_for_a_checkpoint_format_is_accepted(tmp_path: Path) -> None:
    """Only the first four bytes are looked at: any zip (the sandbox loads it later)."""
    inner = raw_zip(tmp_path / "inner.zip", [("meta.json", b"{}")]).read_bytes()
    members = [*good_members(format="sb3", entry="m.zip", class_name=None), ("m.zip", inner)]
    bundle = open_bundle(raw_zip(tmp_path / "b.zip", members), tmp_path / "dest", env=ENV)
    assert bundle.entry_path.read_bytes() == inner


def test_manifest_size_limit_is_inclusive(tmp_path: Path) -> None:
    """The manifest may weigh exactly max_manifest_bytes."""
    raw = json.dumps(manifest_doc()).encode()
    src = raw_zip(tmp_path / "b.zip", [(MANIFEST_NAME, raw), ("agent.py", AGENT_PY)])
    open_bundle(src, tmp_path / "d0", BundleLimits(max_manifest_bytes=len(raw)), ENV)
    limits = BundleLimits(max_manifest_bytes=len(raw) - 1)
    assert refusal(open_bundle, src, tmp_path / "d1", limits, ENV) == (
        f"b.zip: manifest.json is {len(raw)} bytes; at most {len(raw) - 1}"
    )


def test_source_and_destination_refusals(tmp_path: Path) -> None:
    """A missing source names its path; the destination must be new or an empty folder, and
    never a link (extracting through one would write elsewhere)."""
    missing = tmp_path / "nope.zip"
    assert refusal(open_bundle, missing, tmp_path / "d", env=ENV) == (
        f"{missing}: no such bundle file or folder"
    )
    assert refusal(open_bundle, tmp_path / "x.zip", tmp_path / "d", env=ENV).endswith(
        "x.zip: no such bundle file or folder"
    )
    src = raw_zip(tmp_path / "b.zip", good_members())
    (tmp_path / "empty").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "empty")
    assert refusal(open_bundle, src, tmp_path / "link", env=ENV) == (
        f"destination {tmp_path / 'link'} is a link"
    )
    assert not any((tmp_path / "empty").iterdir())
    (tmp_path / "file").write_text("mine")
    assert refusal(open_bundle, src, tmp_path / "file", env=ENV) == (
        f"destination {tmp_path / 'file'} exists and is not an empty folder"
    )
    assert (tmp_path / "file").read_text() == "mine"
    deep = tmp_path / "new" / "deeper" / "dest"
    assert open_bundle(src, deep, env=ENV).root == deep  # parents are created
    bad = tmp_path / "bad.zip"
    bad.write_bytes(b"not a zip at all")
    assert refusal(open_bundle, bad, tmp_path / "d2", env=ENV) == (
        "bad.zip: not a valid zip archive (File is not a zip file)"
    )


def corrupt_zip(path: Path, name: str = "z.bin") -> Path:
    """A bundle whose last member (``name``, after a folder and a file) fails its CRC check:
    it fails mid-extraction, with files and folders already written."""
    members = [*good_members(), ("lib/a/x.py", b"X = 1\n"), ("top.py", b"T")]
    src = raw_zip(path, [*members, (name, os.urandom(3000))])
    data = bytearray(src.read_bytes())
    with zipfile.ZipFile(src) as zf:
        info = zf.getinfo(name)
    data[info.header_offset + 30 + len(name) + 100] ^= 0xFF  # inside its data
    src.write_bytes(bytes(data))
    return src


CORRUPT = "z.bin: corrupt entry (Bad CRC-32 for file 'z.bin')"


def test_a_failed_extraction_into_an_existing_folder_empties_it(tmp_path: Path) -> None:
    """The caller's empty folder stays (empty, ready for a retry); what was written into it,
    files and folders, is gone. A folder open_bundle created is removed."""
    src = corrupt_zip(tmp_path / "b.zip")
    (tmp_path / "dest").mkdir()
    assert refusal(open_bundle, src, tmp_path / "dest", env=ENV) == CORRUPT
    assert (tmp_path / "dest").is_dir() and tree(tmp_path / "dest") == set()
    assert refusal(open_bundle, src, tmp_path / "new", env=ENV) == CORRUPT
    assert not (tmp_path / "new").exists()


def test_a_clean_up_that_fails_never_hides_the_refusal(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Removing the half-written files may fail (a file already gone: a tmp cleaner ran
    meanwhile); the caller still gets the BundleError saying what was wrong, not an OSError."""
    src = corrupt_zip(tmp_path / "b.zip")
    (tmp_path / "dest").mkdir()

    def gone(path: Any, *args: Any, **kwargs: Any) -> None:
        raise FileNotFoundError(2, "No such file or directory", str(path))

    with monkeypatch.context() as m:
        m.setattr(os, "unlink", gone)
        assert refusal(open_bundle, src, tmp_path / "dest", env=ENV) == CORRUPT
        assert refusal(open_bundle, src, tmp_path / "new", env=ENV) == CORRUPT


def test_extraction_never_overwrites_even_past_the_duplicate_check(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Defence in depth: were the duplicate check ever to let a twin member through, the
    second copy cannot replace the first one's file (created exclusively), and the bundle is
    refused and removed."""
    monkeypatch.setattr(bundle_module, "_check_counts", lambda *args: None)
    src = raw_zip(tmp_path / "b.zip", [*good_members(), ("agent.py", b"import os  # twin")])
    assert refusal(open_bundle, src, tmp_path / "dest", env=ENV).startswith(
        "agent.py: corrupt entry ([Errno 17] File exists"
    )
    assert tree(tmp_path) == {"b.zip"}


class Endless(io.RawIOBase):
    """A source that never ends (a huge sparse manifest, a member that lies about its
    size); reading more than 1 MiB of it fails the test instead of eating the memory."""

    served = 0

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: Any) -> int:
        self.served += len(buffer)
        assert self.served <= 1 << 20, "read far past the cap"
        buffer[:] = b"\0" * len(buffer)
        return len(buffer)


def test_copying_stops_right_after_the_cap() -> None:
    """Whatever a source claims, at most the cap plus one 64 KiB read is taken from it before
    the refusal (never the whole source at once)."""
    for cap in (1000, 200_000):  # under one read, and over several
        source = Endless()
        assert refusal(bundle_module._copy_capped, source, None, cap, "big.bin") == (
            f"big.bin holds more than its declared or allowed {cap} bytes"
        )
        assert source.served <= cap + (1 << 16)
        exact = io.BytesIO(b"x" * cap)
        assert bundle_module._copy_capped(exact, None, cap, "ok") == b"x" * cap


def patch_central(src: Path, name: str, offset: int, value: bytes) -> None:
    """Overwrite bytes of ``name``'s central directory record (APPNOTE 4.3.12 offsets)."""
    data = bytearray(src.read_bytes())
    pos = data.find(b"PK\x01\x02")
    while data[pos + 46 : pos + 46 + len(name)] != name.encode():
        pos = data.find(b"PK\x01\x02", pos + 4)
    data[pos + offset : pos + offset + len(value)] = value
    src.write_bytes(bytes(data))


def test_a_zip_needing_a_newer_version_is_refused_not_crashed(tmp_path: Path) -> None:
    """ "Version needed to extract" 10.0 (APPNOTE 4.4.3; zipfile reads up to 6.3): zipfile
    raises NotImplementedError, which used to escape open_bundle as a traceback."""
    src = raw_zip(tmp_path / "b.zip", good_members())
    patch_central(src, "agent.py", 6, (100).to_bytes(2, "little"))
    assert refusal(open_bundle, src, tmp_path / "dest", env=ENV) == (
        "b.zip: not a valid zip archive (zip file version 10.0)"
    )


@pytest.mark.parametrize(
    ("name", "flag", "reason"),
    [
        (MANIFEST_NAME, 0x40, "strong encryption (flag bit 6)"),
        ("w.bin", 0x20, "compressed patched data (flag bit 5)"),
    ],
)
def test_members_flagged_as_unsupported_are_refused_not_crashed(
    tmp_path: Path, name: str, flag: int, reason: str
) -> None:
    """General-purpose flag bits zipfile cannot read (APPNOTE 4.4.4: bit 5 patched data,
    bit 6 strong encryption) on the manifest (read before extraction) or another member
    (read while extracting): a BundleError, and nothing left behind."""
    src = raw_zip(tmp_path / "b.zip", [*good_members(), ("w.bin", b"w" * 100)])
    patch_central(src, name, 8, flag.to_bytes(2, "little"))
    assert refusal(open_bundle, src, tmp_path / "dest", env=ENV) == (
        f"{name}: corrupt entry ({reason})"
    )
    assert tree(tmp_path) == {"b.zip"}


def test_headers_claiming_nothing_compressed_are_a_bomb_by_total(tmp_path: Path) -> None:
    """Members each under the per-member threshold whose headers claim 0 compressed bytes:
    the whole archive's ratio is taken over 1 byte (no division by zero, no pass)."""
    src = raw_zip(tmp_path / "b.zip", [("a.bin", b"a" * 10), ("b.bin", b"b" * 10)])
    for name in ("a.bin", "b.bin"):
        patch_central(src, name, 20, (0).to_bytes(4, "little") + (600_000).to_bytes(4, "little"))
    assert refusal(open_bundle, src, tmp_path / "dest", env=ENV) == (
        "b.zip: the archive expands 1200000:1, over the 100:1 limit (a zip bomb?)"
    )
    limits = BundleLimits(max_ratio=1_000_000)  # between 1.2 MB over 2 bytes and over 1
    assert refusal(open_bundle, src, tmp_path / "dest", limits, ENV) == (
        "b.zip: the archive expands 1200000:1, over the 1000000:1 limit (a zip bomb?)"
    )


def test_a_corrupt_entry_message_is_cut(tmp_path: Path) -> None:
    """The decompressor's complaint is quoted up to 100 characters (a long name stays one
    readable line)."""
    name = "w" * 150 + ".bin"
    src = corrupt_zip(tmp_path / "b.zip", name)
    reason = f"Bad CRC-32 for file {name!r}"[:100]
    assert refusal(open_bundle, src, tmp_path / "dest", env=ENV) == (
        f"{name}: corrupt entry ({reason})"
    )


@pytest.mark.parametrize("name", ["sub/w.bin", MANIFEST_NAME, "agent.py"])
def test_a_folder_file_that_grows_after_the_check_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str
) -> None:
    """A bundle folder still being written (a training run saving into it): a file longer
    than when it was checked (the manifest, the entry or any other) is refused, never read
    or copied past its checked size."""
    src = folder_bundle(tmp_path / "folder", {"sub/w.bin": b"w" * 1000})
    size = (src / name).stat().st_size
    scan = bundle_module._scan_folder

    def scan_then_grow(folder: Path, limits: BundleLimits) -> Any:
        members = scan(folder, limits)
        with (folder / name).open("ab") as fh:
            fh.write(b"\n}\xff" * 100)  # the writer goes on: what was checked is gone
        return members

    monkeypatch.setattr(bundle_module, "_scan_folder", scan_then_grow)
    assert refusal(open_bundle, src, tmp_path / "dest", env=ENV) == (
        f"{name} holds more than its declared or allowed {size} bytes"
    )
    assert not (tmp_path / "dest").exists()


@pytest.mark.parametrize("name", [MANIFEST_NAME, "p" * 150 + ".py"])
def test_a_corrupt_manifest_or_entry_is_refused_before_extraction(
    tmp_path: Path, name: str
) -> None:
    """The manifest and a python entry are read (and CRC-checked) before anything is written;
    the decompressor's complaint is quoted up to 100 characters."""
    src = tmp_path / "b.zip"
    with zipfile.ZipFile(src, "w", compression=zipfile.ZIP_STORED) as zf:  # a flipped byte
        for member, data in good_members(entry="p" * 150 + ".py")[:1]:  # is a CRC error
            zf.writestr(member, data)
        zf.writestr("p" * 150 + ".py", AGENT_PY)
        offset = zf.getinfo(name).header_offset + 30 + len(name) + 5  # inside its data
    raw = bytearray(src.read_bytes())
    raw[offset] ^= 0x01
    src.write_bytes(bytes(raw))
    assert refusal(open_bundle, src, tmp_path / "dest", env=ENV) == (
        f"{name}: corrupt entry ({f'Bad CRC-32 for file {name!r}'[:100]})"
    )
    assert tree(tmp_path) == {"b.zip"}


def test_a_folder_file_swapped_for_a_link_after_the_check_is_not_followed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The time-of-check/time-of-use attack on a folder bundle someone else can write: a
    file checked as regular is swapped for a link to a host secret (of the same size) before
    it is copied. The copy refuses the link instead of copying the secret into the bundle."""
    secret = tmp_path / "secret"
    secret.write_bytes(b"s" * 1000)
    src = folder_bundle(tmp_path / "folder", {"sub/w.bin": b"w" * 1000})
    scan = bundle_module._scan_folder

    def scan_then_swap(folder: Path, limits: BundleLimits) -> Any:
        members = scan(folder, limits)
        (folder / "sub" / "w.bin").unlink()
        (folder / "sub" / "w.bin").symlink_to(secret)
        return members

    monkeypatch.setattr(bundle_module, "_scan_folder", scan_then_swap)
    assert refusal(open_bundle, src, tmp_path / "dest", env=ENV).startswith(
        "sub/w.bin: corrupt entry ([Errno 40] Too many levels of symbolic links"
    )
    assert not (tmp_path / "dest").exists()


def test_extraction_refuses_to_land_outside_even_past_the_name_check(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Defence in depth: were the name check ever to let a zip-slip name through, extraction
    itself still refuses a target outside the destination, and removes what it wrote."""
    monkeypatch.setattr(bundle_module, "unsafe_path", lambda name: None)
    src = raw_zip(tmp_path / "b.zip", [*good_members(), ("../evil.py", b"x")])
    assert refusal(open_bundle, src, tmp_path / "dest", env=ENV) == (
        "entry '../evil.py' would land outside the bundle folder"
    )
    assert tree(tmp_path) == {"b.zip"}


def test_encrypted_member_message(tmp_path: Path) -> None:
    """Encrypted members are refused by name (they cannot be checked)."""
    src = raw_zip(tmp_path / "b.zip", [*good_members(), ("secret.bin", b"x")])
    data = bytearray(src.read_bytes())
    data[data.rfind(b"PK\x01\x02") + 8] |= 0x1  # general purpose flag bit 0: encrypted
    src.write_bytes(bytes(data))
    assert refusal(open_bundle, src, tmp_path / "dest", env=ENV) == (
        "b.zip: entry 'secret.bin' is encrypted"
    )


def test_make_bundle_writes_what_open_bundle_reads(tmp_path: Path) -> None:
    """make_bundle: files from bytes or paths, deflated, the manifest as indented JSON, the
    output's folders created; unsafe or reserved names and a missing entry are refused."""
    m = Manifest.from_dict(manifest_doc())
    helper = tmp_path / "helper.py"
    helper.write_bytes(b"H = 1\n")
    out = make_bundle(tmp_path / "out" / "sub" / "b.zip", m, {"agent.py": AGENT_PY, "h.py": helper})
    with zipfile.ZipFile(out) as zf:
        assert zf.namelist() == [MANIFEST_NAME, "agent.py", "h.py"]
        assert {i.compress_type for i in zf.infolist()} == {zipfile.ZIP_DEFLATED}
        assert zf.read(MANIFEST_NAME) == (json.dumps(m.to_dict(), indent=2) + "\n").encode()
        assert zf.read("h.py") == b"H = 1\n"
    assert refusal(make_bundle, tmp_path / "c.zip", m, {"agent.py": AGENT_PY, "../x": b""}) == (
        "file name '../x' climbs out of the bundle ('..')"
    )
    assert (
        refusal(make_bundle, tmp_path / "c.zip", m, {"agent.py": AGENT_PY, MANIFEST_NAME: b"{}"})
        == "manifest.json is written from the manifest; do not pass it"
    )
    assert refusal(make_bundle, tmp_path / "c.zip", m, {"other.py": AGENT_PY}) == (
        "the manifest's entry 'agent.py' is not among the files"
    )
    assert not (tmp_path / "c.zip").exists()
