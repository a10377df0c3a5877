"""``slipstream bundle init | wrap | check``: make a bundle, check it as the server will.

* ``init DIR --template python|checkpoint``: a working bundle folder to start from. ``python``
  holds a documented ``agent.py`` (the observation layout and the action's meaning in its
  docstring, a simple centre-line driver); ``checkpoint`` holds the shipped PPO racer as
  ``policy.zip`` (our safe checkpoint format) for you to replace with your own. The templates
  are package data (``submissions/templates/``).
* ``wrap CHECKPOINT``: a bundle zip around a checkpoint: ours (``meta.json`` + safetensors),
  or your own stable-baselines3 PPO zip (``--trusted``: loading it unpickles code), which is
  first converted with the same path as ``slipstream export``.
* ``check BUNDLE``: exactly what the leaderboard runs before a version may race ranked:
  :func:`submissions.bundle.open_bundle` (the archive and manifest checks), then the
  validation race (one lap of :data:`VALIDATION_TRACK` against the
  :data:`VALIDATION_OPPONENT` baseline, no penalties, the bundle sandboxed) through the same
  job function and executor as ``slipstream worker``. It prints what would fail, with the
  error detail the owner would see on the site.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import zipfile
from importlib import resources
from pathlib import Path
from typing import Any

from submissions.errors import BundleError, SubmissionError

TEMPLATES = ("python", "checkpoint")
# The server's validation race (leaderboard.settings.Settings defaults; a test keeps them equal).
VALIDATION_TRACK = "oval"
VALIDATION_OPPONENT = "pursuit"
VALIDATION_LAPS = 1
POLICY_FAILURES = ("error", "timeout", "invalid")  # leaderboard.results.POLICY_FAILURES


def register(sub: Any) -> None:
    """Add ``bundle`` (``init``, ``wrap``, ``check``) to the ``slipstream`` subcommands."""
    p = sub.add_parser(
        "bundle",
        help="make a submission bundle (init, wrap) and check it as the server will (check)",
        description="Start a submission bundle from a template, wrap a checkpoint into one, "
        "or run the server's validation on one locally.",
    )
    bsub = p.add_subparsers(dest="bundle_command", required=True, metavar="ACTION")

    i = bsub.add_parser("init", help="write a working bundle folder from a template")
    i.add_argument("dir", type=Path, help="folder to create (must not exist or be empty)")
    i.add_argument("--template", choices=TEMPLATES, default="python", help="what to start from")
    i.add_argument("--name", default=None, help="submission name (default: the folder's name)")
    i.add_argument("--author", default="", help="your name, shown on the leaderboard")
    i.set_defaults(handler=init_command)

    w = bsub.add_parser("wrap", help="turn a checkpoint (ours, or your SB3 zip) into a bundle zip")
    w.add_argument("checkpoint", type=Path, help="a Slipstream checkpoint or an SB3 PPO zip")
    w.add_argument("--name", default=None, help="submission name (default: the checkpoint's)")
    w.add_argument("--author", default="", help="your name, shown on the leaderboard")
    w.add_argument("--out", type=Path, default=None, help="bundle zip (default: NAME-bundle.zip)")
    w.add_argument(
        "--trusted",
        action="store_true",
        help="the SB3 zip is your own: converting it unpickles (runs) its code",
    )
    w.set_defaults(handler=wrap_command)

    c = bsub.add_parser(
        "check",
        help="validate a bundle and run the server's sandboxed validation race",
        description="Runs what the leaderboard runs before ranking a new version: the bundle "
        "checks, then a one-lap validation race against a baseline with the bundle sandboxed. "
        "Exit status 2 if the server would reject it.",
    )
    c.add_argument("bundle", type=Path, help="bundle zip, or a folder with manifest.json")
    c.add_argument("--out", type=Path, default=None, help="keep the race's replay files here")
    c.add_argument("--json", action="store_true", help="print the outcome as JSON")
    c.set_defaults(handler=check_command)


# ---- init -----------------------------------------------------------------------------------


def _fresh_dir(path: Path) -> None:
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        raise SubmissionError(f"{path}: exists and is not an empty folder")
    path.mkdir(parents=True, exist_ok=True)


def _manifest(name: str, author: str, fmt: str, entry: str, description: str) -> Any:
    from arena.version import ENV_VERSION  # noqa: PLC0415 - light: no simulator
    from submissions.bundle import Manifest  # noqa: PLC0415

    return Manifest(
        name=name,
        author=author,
        format=fmt,
        entry=entry,
        env_version=ENV_VERSION,
        description=description,
        env={"lidar_rays": 64, "k_opponents": 3},
    )


def init_bundle(dest: Path, template: str, name: str | None = None, author: str = "") -> Path:
    """Write a working bundle folder from a template; returns ``dest``.

    Raises:
        SubmissionError: ``dest`` is not empty, or the template is unknown.
        BundleError: ``name`` is not a valid submission name.
    """
    if template not in TEMPLATES:
        raise SubmissionError(
            f"unknown template {template!r}; choose one of {', '.join(TEMPLATES)}"
        )
    name = name or dest.resolve().name
    if template == "python":
        manifest = _manifest(name, author, "python", "agent.py", "a centre-line follower")
    else:
        manifest = _manifest(name, author, "slipstream", "policy.zip", "a PPO checkpoint")
    _fresh_dir(dest)
    files = resources.files("submissions") / "templates" / template
    for item in files.iterdir():
        if item.is_file():
            (dest / item.name).write_bytes(item.read_bytes())
    if template == "checkpoint":
        shipped = resources.files("agents") / "data" / "ppo_racer.zip"
        (dest / "policy.zip").write_bytes(shipped.read_bytes())
    text = json.dumps(manifest.to_dict(), indent=2) + "\n"
    (dest / "manifest.json").write_text(text, encoding="utf-8")
    return dest


def init_command(args: argparse.Namespace) -> int:
    """Run ``slipstream bundle init``."""
    dest = init_bundle(args.dir, args.template, args.name, args.author)
    print(f"wrote a {args.template} bundle in {dest}/; next: slipstream bundle check {dest}")
    return 0


# ---- wrap -----------------------------------------------------------------------------------


def wrap_checkpoint(
    checkpoint: Path,
    out: Path | None = None,
    *,
    name: str | None = None,
    author: str = "",
    trusted: bool = False,
) -> tuple[Path, str]:
    """A bundle zip around a checkpoint; returns ``(bundle path, what was done)``.

    An SB3 zip is converted first (:func:`agents.loading.convert_sb3`, ``trusted`` needed);
    a Slipstream checkpoint is read with the strict, code-free reader to take its action
    mode, env version and car (the manifest declares the car it was trained with).

    Raises:
        agents.checkpoint.CheckpointError: not a checkpoint we can read or convert.
        BundleError: the resulting bundle would not pass the server's checks.
    """
    from agents.checkpoint import CheckpointError, read_checkpoint  # noqa: PLC0415 - heavy
    from agents.loading import convert_sb3, detect_format  # noqa: PLC0415
    from submissions.bundle import (  # noqa: PLC0415
        DEFAULT_CAR,
        EnvSpec,
        Manifest,
        car_names,
        make_bundle,
        open_bundle,
    )

    fmt = detect_format(checkpoint)
    with tempfile.TemporaryDirectory(prefix="slipstream-wrap-") as tmp:
        source, how = checkpoint, "wrapped"
        if fmt == "sb3":
            source = convert_sb3(checkpoint, Path(tmp) / "policy.zip", name=name, trusted=trusted)
            how = "converted the SB3 zip to a Slipstream checkpoint and wrapped it"
        elif fmt != "slipstream":
            raise CheckpointError(
                f"{checkpoint}: a {fmt} file; bundles take Slipstream checkpoints (or an SB3 "
                "zip to convert)"
            )
        meta, _ = read_checkpoint(source)
        if meta.observes_perturbation:
            raise CheckpointError(
                f"{checkpoint}: trained on perturbation-aware observations (observe_perturbation: "
                "its car is told its own grip, latency …); ranked races observe the standard "
                "layout without them: train without --observe-perturbation to submit"
            )
        name = name or meta.name
        # The car it learned (a custom car's or an unknown name: the default, and races warn).
        car = meta.car if isinstance(meta.car, str) and meta.car in car_names() else DEFAULT_CAR
        keys = ("lidar_rays", "k_opponents")
        env: dict[str, int] = {k: int(meta.env_config[k]) for k in keys if k in meta.env_config}
        manifest = Manifest(
            name=name,
            author=author,
            format="slipstream",
            entry="policy.zip",
            env_version=meta.env_version,
            obs_mode=meta.obs_mode,
            action_mode=meta.action_mode,
            env=env,
            description=f"{meta.algorithm} checkpoint {checkpoint.name}",
            car=car,
        )
        out = out or Path(f"{name}-bundle.zip")
        make_bundle(out, manifest, {"policy.zip": source})
    with tempfile.TemporaryDirectory(prefix="slipstream-wrap-check-") as tmp:
        try:
            open_bundle(out, Path(tmp) / "b", env=EnvSpec.current())
        except BundleError as err:
            out.unlink(missing_ok=True)
            raise BundleError(f"the wrapped bundle would be refused: {err}") from None
    return out, how


def wrap_command(args: argparse.Namespace) -> int:
    """Run ``slipstream bundle wrap``."""
    out, how = wrap_checkpoint(
        args.checkpoint, args.out, name=args.name, author=args.author, trusted=args.trusted
    )
    print(f"{how}: {out}; next: slipstream bundle check {out}")
    return 0


# ---- check ----------------------------------------------------------------------------------


def validation_failures(result: dict[str, Any], bundle_cars: set[str]) -> list[dict[str, Any]]:
    """The bundle's cars that a validation race would reject (a policy failure), with detail."""
    return [
        {
            "car": car["agent"],
            "reason": car["dnf_reason"],
            "detail": car.get("dnf_detail") or "",
        }
        for car in result.get("cars", [])
        if car["agent"] in bundle_cars
        and car["status"] == "dnf"
        and car["dnf_reason"] in POLICY_FAILURES
    ]


def check_bundle(bundle: Path, out: Path | None = None) -> dict[str, Any]:
    """Run the server's validation on ``bundle``; returns a report (see ``check --json``).

    Report keys: ``ok`` (bool), ``stage`` (``bundle`` or ``race``: where it failed, or
    ``race`` when it passed), ``error`` (one line, or None), ``failures`` (the policy
    failures of the race, each ``{car, reason, detail}``), ``result`` (the race result, or
    None), ``sandbox`` (how the bundle was isolated).
    """
    from submissions.bundle import EnvSpec, open_bundle  # noqa: PLC0415
    from submissions.executors import make_executor  # noqa: PLC0415 - imports the simulator
    from submissions.jobs import Entrant, RaceJob  # noqa: PLC0415

    bundle = bundle.resolve()
    report: dict[str, Any] = {
        "bundle": str(bundle),
        "ok": False,
        "stage": "bundle",
        "error": None,
        "failures": [],
        "result": None,
        "sandbox": None,
    }
    with tempfile.TemporaryDirectory(prefix="slipstream-check-") as tmp:
        try:
            manifest = open_bundle(bundle, Path(tmp) / "bundle", env=EnvSpec.current()).manifest
        except BundleError as err:
            report["error"] = str(err)
            return report
        report["manifest"] = manifest.to_dict()
        report["stage"] = "race"
        out_dir = out.resolve() if out is not None else Path(tmp) / "replays"
        job = RaceJob(
            job_id=f"{manifest.name}-validation",
            entrants=(
                Entrant(name=f"{manifest.name}:check", source=str(bundle)),
                Entrant(name=VALIDATION_OPPONENT, source=VALIDATION_OPPONENT),
            ),
            track=VALIDATION_TRACK,
            out_dir=str(out_dir),
            laps=VALIDATION_LAPS,
            ranked=False,
            record_viser=out is not None,
        )
        (res,) = make_executor(None, workers=1).run([job])
    report["sandbox"] = res.sandbox
    if not res.ok:
        report["error"] = f"the validation race could not run: {res.error}"
        return report
    report["result"] = res.result
    report["failures"] = validation_failures(res.result, {"car_0"})
    report["ok"] = not report["failures"]
    if report["failures"]:
        first = report["failures"][0]
        report["error"] = f"validation race: dnf ({first['reason']})"
    return report


def check_command(args: argparse.Namespace) -> int:
    """Run ``slipstream bundle check``; exit 2 if the server would reject the bundle."""
    from rich.console import Console  # noqa: PLC0415

    console = Console(stderr=args.json)
    with console.status(f"checking {args.bundle} (bundle checks, then a sandboxed race)"):
        report = check_bundle(args.bundle, args.out)
    if args.json:
        sys.stdout.write(json.dumps(report, indent=2) + "\n")
    elif report["result"] is not None:
        from agents.cli import results_table  # noqa: PLC0415

        console.print(results_table(report["result"]))
    if report["ok"]:
        if not args.json:
            console.print(
                f"[green]ok[/]: the server would accept this bundle (sandbox: {report['sandbox']})"
            )
        return 0
    for failure in report["failures"]:
        print(f"car {failure['car']}: dnf ({failure['reason']})", file=sys.stderr)
        if failure["detail"]:
            print(failure["detail"].rstrip(), file=sys.stderr)
    print(
        f"slipstream: error: would be rejected at the {report['stage']} stage: {report['error']}",
        file=sys.stderr,
    )
    return 2


def bundle_for_upload(path: Path, tmp: Path) -> tuple[Path, str | None]:
    """What ``slipstream submit`` uploads for ``path``: a bundle as it is, a bare checkpoint
    wrapped (into ``tmp``), with a note saying so.

    Raises:
        SubmissionError: an SB3 zip or TorchScript file, with the command that wraps it.
    """
    if path.is_dir() or not zipfile.is_zipfile(path):
        return path, None
    with zipfile.ZipFile(path) as zf:
        if "manifest.json" in zf.namelist():
            return path, None
    from agents.loading import detect_format  # noqa: PLC0415 - member names only, no loading

    fmt = detect_format(path)
    if fmt != "slipstream":
        raise SubmissionError(
            f"{path} is a bare {fmt} file, not a bundle; wrap it first: "
            f"slipstream bundle wrap {path} --trusted"
        )
    out, _ = wrap_checkpoint(path, tmp / f"{path.stem}-bundle.zip")
    return out, f"{path} is a bare checkpoint: wrapped it into a bundle ({out.name}) to upload"


__all__ = [
    "bundle_for_upload",
    "check_bundle",
    "init_bundle",
    "validation_failures",
    "wrap_checkpoint",
]
