"""The program that runs INSIDE the sandbox: load one submitted policy, serve reset/act.

Started by :class:`submissions.sandbox.SandboxProcess` as ``python -m submissions.worker``.
It reads the bundle's ``manifest.json``, loads the policy — the only place an uploaded policy
is ever loaded —, says ``READY``, then answers frames of :mod:`submissions.protocol` until
``CLOSE`` or the end of its input:

===============  =====================================================================
format           loaded with
===============  =====================================================================
``slipstream``   :func:`agents.loading.load_policy` (data only)
``sb3``          ``load_policy(..., trusted=True)``: unpickles, which is why it is here
``torchscript``  ``load_policy(..., trusted=True)``: a program, likewise
``python``       the entry file imported as a module; ``class_name`` instantiated with
                 ``env_spec=`` (a dict, see :func:`submissions.remote.make_env_spec`) when
                 its ``__init__`` takes that keyword, else with no arguments
===============  =====================================================================

In seccomp mode (no namespaces) it first confines itself, before reading a byte of the
bundle: parent-death signal, Landlock (read-only paths, one writable temp folder, no TCP,
signals scoped to the sandbox) and the seccomp filter handed over by the host.

The policy's prints go to stdout/stderr, which the host drains and caps; protocol frames go
through the shared-memory channel the host made for it (:mod:`submissions.channel`).
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import importlib.util
import inspect
import json
import os
import signal
import sys
import traceback
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from submissions.channel import WorkerChannel
from submissions.protocol import MAX_TEXT, Kind, ProtocolError, encode, encode_json, encode_text
from submissions.sandbox import apply_seccomp, drop_identity, landlock_restrict


def _args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="submissions.worker", description=__doc__)
    parser.add_argument("--channel", required=True, help="memfd,ring,bell (inherited fds)")
    parser.add_argument("--root", type=Path, required=True, help="the extracted bundle")
    parser.add_argument("--spec", default="{}", help="the env spec, JSON")
    parser.add_argument("--mode", choices=("bwrap", "seccomp"), required=True)
    parser.add_argument("--sandbox-id", default="")
    parser.add_argument("--seccomp-fd", type=int, default=-1)
    parser.add_argument("--drop-uid", type=int, default=-1, help="see sandbox.drop_identity")
    parser.add_argument("--read", action="append", default=[])
    parser.add_argument("--write", action="append", default=[])
    return parser.parse_args(argv)


PROC_FILES = ("status", "stat", "statm", "limits", "maps")  # of itself; never net/ or fd/


def confine(args: argparse.Namespace) -> int:
    """Seccomp mode: confine this process before anything of the bundle is read.

    The host already dropped its groups, gid, capabilities (and, where the interpreter is
    reachable by other users, its uid) and set ``no_new_privs`` and the parent-death signal
    (:func:`submissions.sandbox._preexec`); here: the rest of the uid drop where it must
    follow the exec (``--drop-uid``, :func:`submissions.sandbox.drop_identity`), the
    parent-death signal again (a credential change clears it), Landlock (reads: the given
    paths and a few files of its own ``/proc/<pid>``, never ``/proc/<pid>/net`` nor another
    process; writes: its work folder), then the seccomp filter handed over by the host.

    Returns:
        The Landlock ABI applied (0: none; always 0 in bwrap mode, which needs none).
    """
    if args.mode != "seccomp":
        return 0
    if args.drop_uid > 0:
        drop_identity(args.drop_uid)
    ctypes.CDLL(None).prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG (after it)
    if os.getppid() == 1:  # the host died before the line above
        sys.exit(1)
    with os.fdopen(args.seccomp_fd, "rb") as fh:
        program = fh.read()
    own = f"/proc/{os.getpid()}"
    read = [*args.read, *(f"{own}/{name}" for name in PROC_FILES)]
    abi = landlock_restrict(read, args.write)
    apply_seccomp(program)
    return abi


def load(root: Path, spec: dict[str, Any]) -> tuple[Any, dict[str, Any]]:
    """Load the bundle's policy; returns ``(policy, manifest)``."""
    manifest = json.loads((root / "manifest.json").read_text(encoding="utf-8"))
    fmt = manifest.get("format")
    entry = (root / str(manifest.get("entry", ""))).resolve()
    if not entry.is_relative_to(root.resolve()):
        raise ValueError(f"entry {manifest.get('entry')!r} is outside the bundle")
    if fmt == "python":
        return _load_python(
            root, entry, str(manifest.get("class_name") or "Policy"), spec
        ), manifest
    if fmt not in ("slipstream", "sb3", "torchscript"):
        raise ValueError(f"unknown policy format {fmt!r}")
    from agents.loading import load_policy  # noqa: PLC0415 - only the formats that need it

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # UntrustedCodeWarning: trusted=True is why we are here
        return load_policy(entry, trusted=fmt != "slipstream"), manifest


def _load_python(root: Path, entry: Path, class_name: str, spec: dict[str, Any]) -> Any:
    sys.path.insert(0, str(root))  # the bundle may hold helper modules next to its entry
    module_spec = importlib.util.spec_from_file_location("submission_policy", entry)
    if module_spec is None or module_spec.loader is None:
        raise ImportError(f"cannot import {entry.name}")
    module = importlib.util.module_from_spec(module_spec)
    sys.modules["submission_policy"] = module
    module_spec.loader.exec_module(module)
    cls = getattr(module, class_name, None)
    if cls is None:
        raise AttributeError(f"{entry.name} defines no {class_name!r}")
    try:
        takes_spec = "env_spec" in inspect.signature(cls).parameters
    except (TypeError, ValueError):
        takes_spec = False
    return cls(env_spec=spec) if takes_spec else cls()


def _describe(err: BaseException) -> str:
    return f"{type(err).__name__}: {err}"[:MAX_TEXT]


_ACT = Kind.ACT  # a module name is read faster than an enum's member


def serve(policy: Any, channel: WorkerChannel) -> None:
    """Answer RESET / ACT requests until CLOSE or the host's end; each reply carries its
    request's sequence number (the host counts no other)."""
    last = 0  # READY's
    while (frame := channel.request(last)) is not None:
        last = frame.seq
        if frame.kind == Kind.CLOSE:
            return
        try:
            if frame.kind is _ACT:  # nearly every request
                reply = _action_frame(policy.act(frame.array), frame.seq)
            elif frame.kind == Kind.RESET:
                seed = int(frame.array[0]) if frame.array.size else None
                reset = getattr(policy, "reset", None)
                if reset is not None:
                    reset(seed)
                reply = encode(Kind.OK, seq=frame.seq)
            else:
                raise ProtocolError(f"unexpected {frame.kind.name} frame")
        except Exception as err:  # the policy's bug: report it, the host decides
            traceback.print_exc()
            reply = encode_text(Kind.ERROR, _describe(err), frame.seq)
        try:
            channel.reply(reply)
        except ProtocolError as err:  # an action too large for the reply slot
            channel.reply(encode_text(Kind.INVALID, f"not a valid action: {err}", frame.seq))


def _action_frame(action: Any, seq: int) -> bytes:
    try:
        arr = np.asarray(action)
        if arr.dtype.kind not in "fiu":
            raise ProtocolError(f"action of type {type(action).__name__} / dtype {arr.dtype}")
        return encode(Kind.ACTION, arr, seq)
    except (ProtocolError, TypeError, ValueError, OverflowError) as err:
        return encode_text(Kind.INVALID, f"not a numeric action: {err}", seq)


def main(argv: list[str] | None = None) -> int:
    """Entry point; the exit status is 0 after CLOSE, 1 when the policy failed to load."""
    args = _args(argv)
    landlock = confine(args)
    channel = WorkerChannel(args.channel)
    spec = json.loads(args.spec)
    try:
        policy, manifest = load(args.root, spec)
    except BaseException as err:  # a load may raise anything, SystemExit included
        traceback.print_exc()
        channel.reply(encode_text(Kind.ERROR, f"loading failed: {_describe(err)}"))
        return 1
    hello = {"name": str(manifest.get("name", "")), "format": manifest.get("format")}
    channel.reply(encode_json(Kind.READY, hello | {"landlock": landlock}))
    with contextlib.suppress(BrokenPipeError):
        serve(policy, channel)
    return 0


if __name__ == "__main__":
    status = 1
    try:
        status = main()
    except SystemExit as stop:
        status = stop.code if isinstance(stop.code, int) else 1
    except BaseException:  # whatever ended it, it ends below
        traceback.print_exc()
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)  # now: no thread the policy started keeps the sandbox alive
