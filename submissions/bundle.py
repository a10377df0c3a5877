"""Submission bundles: a zip (or folder) holding ``manifest.json`` and the policy, validated.

A bundle is what a competitor uploads::

    my_racer.zip
    ├── manifest.json      {"schema": 1, "name": "my_racer", "author": "ada",
    │                       "format": "slipstream", "entry": "policy.zip", "obs_mode": "vector",
    │                       "action_mode": "continuous", "env_version": "0.1",
    │                       "env": {"lidar_rays": 64, "k_opponents": 3}}
    └── policy.zip         the policy: our checkpoint, an SB3 zip, TorchScript, or agent.py

=============  ==============================================================================
manifest key   meaning
=============  ==============================================================================
``schema``     1 (the manifest format's version)
``name``       ``[A-Za-z0-9_.-]{1,64}``
``author``     free text, at most 128 characters
``format``     ``slipstream`` (meta.json + safetensors zip), ``sb3`` (stable-baselines3 zip),
               ``torchscript`` (``torch.jit.save`` file) or ``python`` (a ``.py`` file with a
               class exposing ``reset(seed)`` and ``act(obs)``, like a Kaggle agent)
``entry``      relative path of the policy file inside the bundle
``class_name`` python only: the class to instantiate (default ``Policy``)
``obs_mode``   ``vector``
``action_mode`` ``continuous`` or ``discrete``
``env_version`` must equal the evaluating env's ``ENV_VERSION``
``env``        optional declared spaces ``{"lidar_rays": int, "k_opponents": int}``, checked
               against the env's
``description`` optional, at most 4096 characters
``car``        optional car preset the policy drives (:data:`arena.cars.CAR_PRESETS`:
               ``f1tenth``, the default, or ``deepracer``); on the leaderboard a submission
               races only against submissions of the same car
=============  ==============================================================================

:func:`open_bundle` checks everything it can *before* writing a byte: the archive's size,
member count, each member's name (no absolute paths, ``..``, backslashes, drive letters or
control characters), type (no symlinks, devices or FIFOs), duplicates, encryption and
compression method, sizes (per member and in total) and compression ratios (zip bombs), then
the manifest (strict JSON, schema, declared spaces against the env) and that the entry exists
and looks like its format. Only then does it extract, member by member, into a fresh
destination folder, counting the bytes it really writes. Any failure raises
:class:`~submissions.errors.BundleError` with one line saying what is wrong, and leaves nothing
behind. Nothing here loads, unpickles or imports the policy: that happens only in the sandbox.

>>> Manifest.from_dict({"schema": 1, "name": "demo", "author": "ada", "format": "python",
...     "entry": "agent.py", "obs_mode": "vector", "action_mode": "continuous",
...     "env_version": "0.1"}).class_name
'Policy'
"""

from __future__ import annotations

import io
import json
import os
import re
import shutil
import stat
import zipfile
import zlib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from submissions.errors import BundleError

MANIFEST_NAME = "manifest.json"
MANIFEST_SCHEMA = 1
FORMATS = ("slipstream", "sb3", "torchscript", "python")
OBS_MODES = ("vector",)
ACTION_MODES = ("continuous", "discrete")
ZIP_FORMATS = ("slipstream", "sb3", "torchscript")  # entry files that are zip archives
# A bundle's name names folders and files (evaluate's output folder, job ids): it starts with
# a letter or digit, so "", ".", "..", ".hidden" and "-option" are refused; no "/" anywhere.
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,63}")
MAX_AUTHOR = 128  # characters
MAX_DESCRIPTION = 4096  # characters
MAX_ENV_VERSION = 32  # characters
MAX_PATH = 512  # characters in a member's path
MAX_DEPTH = 16  # folders in a member's path
ENV_KEYS = {"lidar_rays": (1, 4096), "k_opponents": (0, 16)}  # declared space: allowed range
REQUIRED = (
    "schema",
    "name",
    "author",
    "format",
    "entry",
    "obs_mode",
    "action_mode",
    "env_version",
)
OPTIONAL = ("class_name", "env", "description", "car")
DEFAULT_CAR = "f1tenth"  # = arena.cars.DEFAULT_CAR (tested equal; this module stays light)
ZIP_MAGIC = b"PK\x03\x04"
_CHUNK = 1 << 16
# What zipfile raises on a damaged or hostile archive; NotImplementedError: a "version needed
# to extract" above its own, or a member flagged as patched data or strongly encrypted.
_ZIP_ERRORS = (zipfile.BadZipFile, zlib.error, EOFError, OSError, NotImplementedError)


@dataclass(frozen=True)
class BundleLimits:
    """What a bundle may weigh (bytes) before anything is extracted.

    Attributes:
        max_archive_bytes: the uploaded zip, or a folder's files in total.
        max_total_bytes: all members uncompressed, in total (a zip bomb by total).
        max_member_bytes: one member uncompressed.
        max_members: entries in the archive, folders included.
        max_ratio: uncompressed / compressed, per member and for the whole archive (a zip
            bomb by ratio); weights barely compress, source code about 4:1.
        ratio_min_bytes: members (and archives) smaller than this are not held to
            ``max_ratio``: a tiny file of zeros is not a bomb.
        max_manifest_bytes: ``manifest.json``.
    """

    max_archive_bytes: int = 64 << 20
    max_total_bytes: int = 256 << 20
    max_member_bytes: int = 128 << 20
    max_members: int = 256
    max_ratio: float = 100.0
    ratio_min_bytes: int = 1 << 20
    max_manifest_bytes: int = 64 << 10


@dataclass(frozen=True)
class EnvSpec:
    """The env a bundle will race in: what its manifest's declarations are checked against.

    Attributes:
        env_version: the env's ``ENV_VERSION``.
        lidar_rays: lidar rays in the vector observation.
        k_opponents: opponents in the vector observation.
        action_modes: action modes the evaluation can drive.
        compatible_versions: other env versions whose observations and actions mean the same
            (a bundle made for one of them is accepted too).
    """

    env_version: str
    lidar_rays: int = 64
    k_opponents: int = 3
    action_modes: tuple[str, ...] = ("continuous",)
    compatible_versions: tuple[str, ...] = ()

    @classmethod
    def current(cls) -> EnvSpec:
        """The evaluation env of this installation (:mod:`arena.version`: no pybullet)."""
        from arena.version import (  # noqa: PLC0415 - keep bundle.py light to import
            COMPATIBLE_ENV_VERSIONS,
            ENV_VERSION,
        )

        return cls(env_version=ENV_VERSION, compatible_versions=COMPATIBLE_ENV_VERSIONS)


@dataclass(frozen=True)
class Manifest:
    """A bundle's ``manifest.json`` (see the module docstring for each field)."""

    name: str
    author: str
    format: str
    entry: str
    env_version: str
    obs_mode: str = "vector"
    action_mode: str = "continuous"
    class_name: str = "Policy"
    env: Mapping[str, int] = field(default_factory=dict)
    description: str = ""
    schema: int = MANIFEST_SCHEMA
    car: str = DEFAULT_CAR

    def __post_init__(self) -> None:
        _check_manifest(self)

    @classmethod
    def from_dict(cls, doc: Any) -> Manifest:
        """Build and validate a manifest from its JSON document.

        Raises:
            BundleError: not an object, a missing or unknown key, or a bad value.
        """
        if not isinstance(doc, dict):
            raise BundleError(f"{MANIFEST_NAME} must be a JSON object, not {_kind(doc)}")
        unknown = sorted(set(doc) - set(REQUIRED) - set(OPTIONAL))
        if unknown:
            raise BundleError(f"{MANIFEST_NAME}: unknown key(s) {', '.join(map(repr, unknown))}")
        missing = [k for k in REQUIRED if k not in doc]
        if missing:
            raise BundleError(f"{MANIFEST_NAME}: missing key(s) {', '.join(missing)}")
        if doc["schema"] != MANIFEST_SCHEMA or isinstance(doc["schema"], bool):
            raise BundleError(
                f"{MANIFEST_NAME}: schema {_short(doc['schema'])} is not supported "
                f"(this version reads schema {MANIFEST_SCHEMA})"
            )
        if "class_name" in doc and doc.get("format") != "python":
            raise BundleError(f"{MANIFEST_NAME}: class_name applies to the python format only")
        env = doc.get("env", {})
        if not isinstance(env, dict):
            raise BundleError(f"{MANIFEST_NAME}: env must be an object, not {_kind(env)}")
        return cls(
            name=doc["name"],
            author=doc["author"],
            format=doc["format"],
            entry=doc["entry"],
            env_version=doc["env_version"],
            obs_mode=doc["obs_mode"],
            action_mode=doc["action_mode"],
            class_name=doc.get("class_name", "Policy"),
            env=dict(env),
            description=doc.get("description", ""),
            car=doc.get("car", DEFAULT_CAR),
        )

    def to_dict(self) -> dict[str, Any]:
        """The JSON document (optional keys only when they carry something)."""
        doc: dict[str, Any] = {
            "schema": self.schema,
            "name": self.name,
            "author": self.author,
            "format": self.format,
            "entry": self.entry,
            "obs_mode": self.obs_mode,
            "action_mode": self.action_mode,
            "env_version": self.env_version,
        }
        if self.format == "python":
            doc["class_name"] = self.class_name
        if self.env:
            doc["env"] = dict(self.env)
        if self.description:
            doc["description"] = self.description
        if self.car != DEFAULT_CAR:
            doc["car"] = self.car
        return doc


@dataclass(frozen=True)
class Bundle:
    """An extracted, validated bundle: ``root`` holds ``manifest.json`` and the policy."""

    root: Path
    manifest: Manifest

    @property
    def entry_path(self) -> Path:
        """The policy file on disk."""
        return self.root / self.manifest.entry


# ---- the manifest ---------------------------------------------------------------------------


def _kind(value: Any) -> str:
    return "null" if value is None else type(value).__name__


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _text(m: Manifest, key: str, limit: int, pattern: re.Pattern[str] | None = None) -> str:
    value = getattr(m, key)
    if not isinstance(value, str):
        raise BundleError(f"{MANIFEST_NAME}: {key} must be a string, not {_kind(value)}")
    if len(value) > limit:
        raise BundleError(f"{MANIFEST_NAME}: {key} is {len(value)} characters; at most {limit}")
    if pattern is not None and not pattern.fullmatch(value):
        raise BundleError(f"{MANIFEST_NAME}: {key} {_short(value)} must match {pattern.pattern}")
    if any(ord(ch) < 32 and ch not in "\n\t" for ch in value):
        raise BundleError(f"{MANIFEST_NAME}: {key} contains control characters")
    return value


def _choice(m: Manifest, key: str, allowed: tuple[str, ...]) -> None:
    value = getattr(m, key)
    if value not in allowed:
        raise BundleError(
            f"{MANIFEST_NAME}: {key} {_short(value)} is not one of {', '.join(allowed)}"
        )


def _check_manifest(m: Manifest) -> None:
    """Field by field; raises :class:`BundleError` naming the first bad one."""
    if m.schema != MANIFEST_SCHEMA:
        raise BundleError(f"{MANIFEST_NAME}: schema {_short(m.schema)} is not supported")
    _text(m, "name", 64, NAME_PATTERN)
    _text(m, "author", MAX_AUTHOR)
    _text(m, "description", MAX_DESCRIPTION)
    _text(m, "env_version", MAX_ENV_VERSION)
    _choice(m, "format", FORMATS)
    _choice(m, "obs_mode", OBS_MODES)
    _choice(m, "action_mode", ACTION_MODES)
    _text(m, "car", 32)
    _choice(m, "car", car_names())
    entry = _text(m, "entry", MAX_PATH)
    problem = unsafe_path(entry)
    if problem:
        raise BundleError(f"{MANIFEST_NAME}: entry {_short(entry)} {problem}")
    if entry == MANIFEST_NAME:
        raise BundleError(f"{MANIFEST_NAME}: entry cannot be the manifest itself")
    if m.format == "python":
        _text(m, "class_name", 64, IDENTIFIER)
        if not entry.endswith(".py"):
            raise BundleError(f"{MANIFEST_NAME}: a python bundle's entry must be a .py file")
    if not isinstance(m.env, Mapping):
        raise BundleError(f"{MANIFEST_NAME}: env must be an object")
    for key, value in m.env.items():
        if key not in ENV_KEYS:
            raise BundleError(
                f"{MANIFEST_NAME}: env key {_short(key)} is unknown "
                f"(declarable: {', '.join(ENV_KEYS)})"
            )
        lo, hi = ENV_KEYS[key]
        if not isinstance(value, int) or isinstance(value, bool) or not lo <= value <= hi:
            raise BundleError(
                f"{MANIFEST_NAME}: env.{key} must be an integer in [{lo}, {hi}], "
                f"not {_short(value)}"
            )


def car_names() -> tuple[str, ...]:
    """The car presets a manifest may declare (:data:`arena.cars.CAR_PRESETS`' names)."""
    from arena.cars import CAR_PRESETS  # noqa: PLC0415 - no pybullet; keep bundle.py light

    return tuple(CAR_PRESETS)


def check_env(manifest: Manifest, env: EnvSpec) -> None:
    """The manifest's declared env version and spaces match the evaluating env.

    Raises:
        BundleError: a mismatch, naming both values.
    """
    if manifest.env_version not in (env.env_version, *env.compatible_versions):
        raise BundleError(
            f"bundle {manifest.name!r} was made for env version {manifest.env_version!r}; "
            f"this evaluation runs env version {env.env_version!r}"
        )
    if manifest.action_mode not in env.action_modes:
        raise BundleError(
            f"bundle {manifest.name!r} declares action_mode {manifest.action_mode!r}; this "
            f"evaluation drives {' or '.join(env.action_modes)} actions"
        )
    for key in ENV_KEYS:
        declared, actual = manifest.env.get(key), getattr(env, key)
        if declared is not None and declared != actual:
            raise BundleError(
                f"bundle {manifest.name!r} declares {key}={declared}; the env has {key}={actual}"
            )


def _strict_object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    doc: dict[str, Any] = {}
    for key, value in pairs:
        if key in doc:
            raise ValueError(f"duplicate key {key!r}")
        doc[key] = value
    return doc


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not valid JSON")


def parse_manifest(raw: bytes) -> Manifest:
    """A manifest from the bytes of ``manifest.json`` (strict UTF-8 JSON, no duplicate keys).

    Raises:
        BundleError: not JSON, or not a valid manifest.
    """
    try:
        doc = json.loads(
            raw.decode("utf-8"),
            object_pairs_hook=_strict_object,
            parse_constant=_reject_constant,
        )
    except (UnicodeDecodeError, ValueError, RecursionError) as err:
        reason = "nested too deeply" if isinstance(err, RecursionError) else str(err)
        raise BundleError(f"{MANIFEST_NAME} is not valid JSON: {reason[:120]}") from None
    return Manifest.from_dict(doc)


def read_manifest(root: Path, limits: BundleLimits = BundleLimits()) -> Manifest:
    """The validated manifest of an extracted bundle (or bundle folder) at ``root``.

    Raises:
        BundleError: missing, too large, a link, or invalid.
    """
    path = Path(root) / MANIFEST_NAME
    return parse_manifest(_read_file(path, limits.max_manifest_bytes, MANIFEST_NAME))


# ---- member names and types -----------------------------------------------------------------


def unsafe_path(name: str) -> str | None:
    """Why ``name`` is not a plain relative path inside the bundle, or None when it is.

    >>> unsafe_path("weights/policy.zip") is None
    True
    >>> unsafe_path("../etc/passwd")
    "climbs out of the bundle ('..')"
    """
    if not name:
        return "is empty"
    if len(name) > MAX_PATH:
        return f"is longer than {MAX_PATH} characters"
    if any(ord(ch) < 32 or ord(ch) == 127 for ch in name):
        return "contains control characters"
    if name.startswith("/") or re.match(r"[A-Za-z]:", name):
        return "is absolute"
    if "\\" in name:
        return "contains a backslash"
    parts = name.split("/")
    if ".." in parts:
        return "climbs out of the bundle ('..')"
    if any(p in ("", ".") for p in parts):
        return "has an empty or '.' path component"
    if len(parts) > MAX_DEPTH:
        return f"is more than {MAX_DEPTH} folders deep"
    return None


@dataclass(frozen=True)
class _Member:
    """One file to extract: its path in the bundle, size, and how to read it."""

    name: str
    size: int
    info: zipfile.ZipInfo | None = None  # zip member
    path: Path | None = None  # folder file


def _zip_mode(info: zipfile.ZipInfo) -> int:
    return (info.external_attr >> 16) & 0xFFFF if info.create_system == 3 else 0


def _check_counts(members: list[_Member], limits: BundleLimits, label: str) -> None:
    total = 0
    for m in members:
        if m.size > limits.max_member_bytes:
            raise BundleError(
                f"{label}: {m.name} is {m.size} bytes uncompressed, over the "
                f"{limits.max_member_bytes}-byte limit per file"
            )
        total += m.size
    if total > limits.max_total_bytes:
        raise BundleError(
            f"{label}: {total} bytes uncompressed in total, over the "
            f"{limits.max_total_bytes}-byte limit (a zip bomb?)"
        )
    names = [m.name for m in members]
    lowered: dict[str, str] = {}
    for name in names:
        if name.casefold() in lowered:
            raise BundleError(
                f"{label}: duplicate entry {name!r} (also {lowered[name.casefold()]!r})"
            )
        lowered[name.casefold()] = name
    folders = {"/".join(n.split("/")[:i]) for n in names for i in range(1, n.count("/") + 1)}
    clash = sorted(folders & set(names))
    if clash:
        raise BundleError(f"{label}: {clash[0]!r} is both a file and a folder")


def _scan_zip(src: Path, limits: BundleLimits) -> tuple[zipfile.ZipFile, list[_Member]]:
    """Open ``src`` and check every member's header; returns the files to extract."""
    label = src.name
    size = src.stat().st_size
    if size > limits.max_archive_bytes:
        raise BundleError(
            f"{label}: {size} bytes, over the {limits.max_archive_bytes}-byte upload limit"
        )
    try:
        zf = zipfile.ZipFile(src)
        infos = zf.infolist()
    except (*_ZIP_ERRORS, ValueError) as err:
        raise BundleError(f"{label}: not a valid zip archive ({str(err)[:100]})") from None
    try:
        if len(infos) > limits.max_members:
            raise BundleError(
                f"{label}: {len(infos)} entries, over the limit of {limits.max_members}"
            )
        members: list[_Member] = []
        packed = 0
        for info in infos:
            name = info.filename
            is_dir = name.endswith("/")
            problem = unsafe_path(name[:-1] if is_dir else name)
            if problem:
                raise BundleError(f"{label}: entry {_short(name)} {problem}; refusing the bundle")
            kind = stat.S_IFMT(_zip_mode(info))
            if kind == stat.S_IFLNK:
                raise BundleError(f"{label}: entry {name!r} is a symbolic link; links are refused")
            if kind not in (0, stat.S_IFREG, stat.S_IFDIR):
                raise BundleError(f"{label}: entry {name!r} is not a regular file")
            if info.flag_bits & 0x1:
                raise BundleError(f"{label}: entry {name!r} is encrypted")
            if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
                raise BundleError(
                    f"{label}: entry {name!r} uses compression method {info.compress_type}; "
                    "only stored and deflated entries are accepted"
                )
            if is_dir or kind == stat.S_IFDIR:
                if info.file_size:
                    raise BundleError(f"{label}: folder entry {name!r} carries data")
                continue
            ratio = info.file_size / max(info.compress_size, 1)
            if info.file_size > limits.ratio_min_bytes and ratio > limits.max_ratio:
                raise BundleError(
                    f"{label}: entry {name!r} compresses {ratio:.0f}:1, over the "
                    f"{limits.max_ratio:.0f}:1 limit (a zip bomb?)"
                )
            packed += info.compress_size
            members.append(_Member(name, info.file_size, info=info))
        _check_counts(members, limits, label)
        total = sum(m.size for m in members)
        if total > limits.ratio_min_bytes and total / max(packed, 1) > limits.max_ratio:
            raise BundleError(
                f"{label}: the archive expands {total / max(packed, 1):.0f}:1, over the "
                f"{limits.max_ratio:.0f}:1 limit (a zip bomb?)"
            )
    except BaseException:
        zf.close()
        raise
    return zf, members


def _scan_folder(src: Path, limits: BundleLimits) -> list[_Member]:
    """Walk a bundle folder without following links; returns the files to copy."""
    label = src.name
    members: list[_Member] = []
    count = 0
    for dirpath, dirnames, filenames in os.walk(src, followlinks=False):
        here = Path(dirpath)
        for name in sorted(dirnames) + sorted(filenames):
            path = here / name
            rel = path.relative_to(src).as_posix()
            count += 1
            if count > limits.max_members:
                raise BundleError(f"{label}: more than {limits.max_members} entries")
            problem = unsafe_path(rel)
            if problem:
                raise BundleError(f"{label}: entry {_short(rel)} {problem}")
            st = path.lstat()
            if stat.S_ISLNK(st.st_mode):
                raise BundleError(f"{label}: {rel} is a symbolic link; links are refused")
            if stat.S_ISREG(st.st_mode):
                members.append(_Member(rel, st.st_size, path=path))
            elif not stat.S_ISDIR(st.st_mode):
                raise BundleError(f"{label}: {rel} is not a regular file")
    total = sum(m.size for m in members)
    if total > limits.max_archive_bytes:
        raise BundleError(
            f"{label}: {total} bytes of files, over the {limits.max_archive_bytes}-byte limit"
        )
    _check_counts(members, limits, label)
    return members


# ---- reading and extracting -----------------------------------------------------------------


def _copy_capped(src: IO[bytes], dst: IO[bytes] | None, cap: int, label: str) -> bytes:
    """Copy at most ``cap`` bytes (error past that); returns them when ``dst`` is None."""
    kept = io.BytesIO()
    n = 0
    while chunk := src.read(_CHUNK):
        n += len(chunk)
        if n > cap:
            raise BundleError(f"{label} holds more than its declared or allowed {cap} bytes")
        (dst or kept).write(chunk)
    return kept.getvalue()


def _read_file(path: Path, cap: int, label: str) -> bytes:
    try:
        # O_NONBLOCK: opening a FIFO must not wait for a writer (reads of a file ignore it)
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOFOLLOW", 0))
    except FileNotFoundError:
        raise BundleError(f"no {label} in the bundle") from None
    except OSError as err:
        raise BundleError(f"{label}: cannot be read ({err.strerror}; a link?)") from None
    # Checked on the descriptor, before a file object: fdopen refuses a folder with an OSError.
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise BundleError(f"{label} is not a regular file")
    with os.fdopen(fd, "rb") as fh:
        return _copy_capped(fh, None, cap, label)


def _open_member(zf: zipfile.ZipFile | None, m: _Member) -> IO[bytes]:
    if m.info is not None and zf is not None:
        return zf.open(m.info)
    assert m.path is not None
    fd = os.open(m.path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
    return os.fdopen(fd, "rb")


def _read_member(zf: zipfile.ZipFile | None, m: _Member, cap: int, head: bool = False) -> bytes:
    """The member's bytes (at most ``cap``; more is an error unless ``head``: the first ones)."""
    try:
        with _open_member(zf, m) as fh:
            if head:
                return fh.read(cap)
            return _copy_capped(fh, None, min(cap, m.size), m.name)
    except _ZIP_ERRORS as err:
        raise BundleError(f"{m.name}: corrupt entry ({str(err)[:100]})") from None


def _check_entry(zf: zipfile.ZipFile | None, members: list[_Member], manifest: Manifest) -> None:
    by_name = {m.name: m for m in members}
    entry = by_name.get(manifest.entry)
    if entry is None:
        raise BundleError(
            f"the manifest's entry {manifest.entry!r} is not a file in the bundle "
            f"(files: {', '.join(sorted(by_name)[:8])})"
        )
    if manifest.format in ZIP_FORMATS:
        head = _read_member(zf, entry, len(ZIP_MAGIC), head=True)
        if head != ZIP_MAGIC:
            raise BundleError(
                f"entry {manifest.entry!r} is not a zip archive, as a {manifest.format} "
                "policy file must be"
            )
    elif manifest.format == "python":
        try:
            _read_member(zf, entry, entry.size).decode("utf-8")
        except UnicodeDecodeError:
            raise BundleError(f"entry {manifest.entry!r} is not UTF-8 Python source") from None


def _prepare_dest(dest: Path) -> None:
    if dest.is_symlink():
        raise BundleError(f"destination {dest} is a link")
    if dest.exists():
        if not dest.is_dir() or any(dest.iterdir()):
            raise BundleError(f"destination {dest} exists and is not an empty folder")
    else:
        dest.mkdir(parents=True)


def _extract(zf: zipfile.ZipFile | None, members: list[_Member], dest: Path) -> None:
    root = dest.resolve()
    for m in members:
        target = (root / m.name).resolve()
        if root not in target.parents:  # unsafe_path already rules this out; belt and braces
            raise BundleError(f"entry {m.name!r} would land outside the bundle folder")
        target.parent.mkdir(parents=True, exist_ok=True)
        flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
        try:
            with _open_member(zf, m) as src, os.fdopen(os.open(target, flags, 0o644), "wb") as dst:
                _copy_capped(src, dst, m.size, m.name)
        except _ZIP_ERRORS as err:
            raise BundleError(f"{m.name}: corrupt entry ({str(err)[:100]})") from None


def open_bundle(
    src: Path,
    dest: Path,
    limits: BundleLimits = BundleLimits(),
    env: EnvSpec | None = None,
) -> Bundle:
    """Validate a bundle zip or folder, then extract (or copy) it into ``dest``.

    Args:
        src: the uploaded ``.zip``, or a bundle folder.
        dest: a folder that does not exist yet (or is empty); it becomes the bundle's root.
        limits: size, count and ratio limits.
        env: the env to check the manifest against; default :meth:`EnvSpec.current` (which
            imports the simulator: pass one explicitly in a process that must not).

    Returns:
        The extracted bundle.

    Raises:
        BundleError: one line saying what is wrong; ``dest`` is then left as it was.
    """
    src, dest = Path(src), Path(dest)
    if not src.exists():
        raise BundleError(f"{src}: no such bundle file or folder")
    zf: zipfile.ZipFile | None = None
    if src.is_dir():
        members = _scan_folder(src, limits)
    else:
        zf, members = _scan_zip(src, limits)
    try:
        manifest_member = next((m for m in members if m.name == MANIFEST_NAME), None)
        if manifest_member is None:
            raise BundleError(f"{src.name}: no {MANIFEST_NAME} at the bundle's root")
        if manifest_member.size > limits.max_manifest_bytes:
            raise BundleError(
                f"{src.name}: {MANIFEST_NAME} is {manifest_member.size} bytes; at most "
                f"{limits.max_manifest_bytes}"
            )
        manifest = parse_manifest(_read_member(zf, manifest_member, limits.max_manifest_bytes))
        check_env(manifest, env or EnvSpec.current())
        _check_entry(zf, members, manifest)
        created = not dest.exists()
        _prepare_dest(dest)
        try:
            _extract(zf, members, dest)
        except BaseException:
            _empty(dest, remove=created)
            raise
    finally:
        if zf is not None:
            zf.close()
    return Bundle(root=dest, manifest=manifest)


def _empty(folder: Path, remove: bool) -> None:
    if remove:
        shutil.rmtree(folder, ignore_errors=True)
        return
    for child in folder.iterdir():
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child, ignore_errors=True)
        else:
            child.unlink(missing_ok=True)


# ---- writing --------------------------------------------------------------------------------


def _iter_files(files: Mapping[str, Path | bytes]) -> Iterator[tuple[str, bytes]]:
    for name, content in files.items():
        problem = unsafe_path(name)
        if problem:
            raise BundleError(f"file name {name!r} {problem}")
        if name == MANIFEST_NAME:
            raise BundleError(f"{MANIFEST_NAME} is written from the manifest; do not pass it")
        yield name, content if isinstance(content, bytes) else Path(content).read_bytes()


def make_bundle(out: Path, manifest: Manifest, files: Mapping[str, Path | bytes]) -> Path:
    """Write a bundle zip: ``manifest.json`` plus ``files`` (bundle path → file or bytes).

    Raises:
        BundleError: an unsafe file name, or the manifest's entry is not among ``files``.
    """
    if manifest.entry not in files:
        raise BundleError(f"the manifest's entry {manifest.entry!r} is not among the files")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    payload = list(_iter_files(files))
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr(MANIFEST_NAME, json.dumps(manifest.to_dict(), indent=2) + "\n")
        for name, data in payload:
            zf.writestr(name, data)
    return out


__all__ = [
    "MANIFEST_NAME",
    "Bundle",
    "BundleLimits",
    "EnvSpec",
    "Manifest",
    "check_env",
    "make_bundle",
    "open_bundle",
    "parse_manifest",
    "read_manifest",
    "unsafe_path",
]
