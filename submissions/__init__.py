"""Submissions: bundles, the sandbox, sandboxed race jobs, and the executors that run them.

==========================  ============================================================
module                      holds
==========================  ============================================================
:mod:`submissions.bundle`   the bundle format (zip or folder + ``manifest.json``) and its
                            validation before extraction
:mod:`submissions.sandbox`  bubblewrap / seccomp sandboxes for one policy process
:mod:`submissions.remote`   :class:`SandboxedPolicy`: a Policy living in a sandbox
:mod:`submissions.protocol`  the frames a race and a sandboxed policy exchange
:mod:`submissions.channel`  the shared memory and wake-up pipes the frames travel through
:mod:`submissions.worker`   the program inside the sandbox: loads the policy, answers
:mod:`submissions.jobs`     :class:`RaceJob` (plain data) and :func:`run_race_job`
:mod:`submissions.executors`  local process pool and Ray executors
:mod:`submissions.viser_replay`  ``.viser`` 3D replays from replay logs
==========================  ============================================================

``import submissions`` stays light (no simulator, no torch, no viser): the names below load
on first use, so the leaderboard's web process can validate bundles and build jobs.
"""

from __future__ import annotations

import importlib
from typing import Any

_LAZY = {
    "Bundle": "submissions.bundle",
    "BundleLimits": "submissions.bundle",
    "EnvSpec": "submissions.bundle",
    "Manifest": "submissions.bundle",
    "make_bundle": "submissions.bundle",
    "open_bundle": "submissions.bundle",
    "read_manifest": "submissions.bundle",
    "Entrant": "submissions.jobs",
    "JobResult": "submissions.jobs",
    "RaceJob": "submissions.jobs",
    "run_race_job": "submissions.jobs",
    "LocalExecutor": "submissions.executors",
    "RayExecutor": "submissions.executors",
    "make_executor": "submissions.executors",
    "write_viser": "submissions.viser_replay",
    "SandboxLimits": "submissions.sandbox",
    "sandbox_mode": "submissions.sandbox",
    "SandboxedPolicy": "submissions.remote",
    "PolicyFailure": "submissions.remote",
    "SubmissionError": "submissions.errors",
    "BundleError": "submissions.errors",
    "SandboxError": "submissions.errors",
}

__all__ = [
    "Bundle",
    "BundleError",
    "BundleLimits",
    "Entrant",
    "EnvSpec",
    "JobResult",
    "LocalExecutor",
    "Manifest",
    "PolicyFailure",
    "RaceJob",
    "RayExecutor",
    "SandboxError",
    "SandboxLimits",
    "SandboxedPolicy",
    "SubmissionError",
    "make_bundle",
    "make_executor",
    "open_bundle",
    "read_manifest",
    "run_race_job",
    "sandbox_mode",
    "write_viser",
]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'submissions' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)
