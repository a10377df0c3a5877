"""A race's events as a timeline, and each car's penalties with what they were for.

The replay log records events per car (:mod:`arena.replay`): ``lap`` (``lap``, ``lap_time``
s), ``collision`` (``other``, ``at_fault``, ``closing_speed`` m/s; both cars of a contact
record it), ``off_track``, ``finish`` and ``dnf`` (``reason``). The timeline shows a contact
once, naming both cars and who was to blame. In ranked races each off-track excursion costs
:data:`~leaderboard.results.PENALTY_SECONDS` ``["off_track"]`` and each collision a car caused
``["collision"]`` (DeepRacer's rules, as :mod:`arena.race` applies them).

>>> names = {"car_0": "ada", "car_1": "bob"}
>>> ev = [{"t": 3.0, "type": "collision", "car": "car_0", "other": "car_1", "at_fault": True},
...       {"t": 3.0, "type": "collision", "car": "car_1", "other": "car_0", "at_fault": False}]
>>> [e.text for e in timeline(ev, names)]
['ada hit bob (ada at fault)']
>>> [(p.seconds, p.reason) for p in penalties(ev, ranked=True)["car_0"]]
[(5.0, 'collision with car_1 (at fault) at 3.0 s')]
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from pydantic import BaseModel

from leaderboard.results import PENALTY_SECONDS


class TimelineEvent(BaseModel):
    """One line of a race's timeline.

    Attributes:
        t: simulated time, s (the replay's clock).
        type: ``lap``, ``collision``, ``off_track``, ``finish`` or ``dnf``.
        car: the car it concerns (``car_i``); for a collision, the one at fault if any.
        other: the other car of a collision.
        at_fault: for a collision, whether ``car`` was to blame.
        text: what happened, in words.
    """

    t: float
    type: str
    car: str
    other: str | None = None
    at_fault: bool | None = None
    text: str


class Penalty(BaseModel):
    """Time added to a car's race time: ``seconds`` for ``reason``, at ``t`` s."""

    t: float
    seconds: float
    reason: str


def _name(names: Mapping[str, str], car: Any) -> str:
    return names.get(str(car), str(car))


def timeline(events: Sequence[Mapping[str, Any]], names: Mapping[str, str]) -> list[TimelineEvent]:
    """The race's events in time order, each contact once (see the module docstring)."""
    out: list[TimelineEvent] = []
    seen: set[tuple[float, frozenset[str]]] = set()
    for e in sorted(events, key=lambda e: float(e.get("t", 0.0))):
        t, kind, car = float(e.get("t", 0.0)), str(e.get("type", "")), str(e.get("car", ""))
        who = _name(names, car)
        if kind == "lap":
            lap_time = e.get("lap_time")
            time = f" in {float(lap_time):.3f} s" if lap_time is not None else ""
            out.append(
                TimelineEvent(t=t, type=kind, car=car, text=f"{who} lap {e.get('lap')}{time}")
            )
        elif kind == "collision":
            other = str(e.get("other", ""))
            key = (round(t, 3), frozenset((car, other)))
            if key in seen:
                continue
            seen.add(key)
            partner = next(
                (
                    p
                    for p in events
                    if p.get("type") == "collision"
                    and str(p.get("car")) == other
                    and str(p.get("other")) == car
                    and abs(float(p.get("t", 0.0)) - t) < 1e-6
                ),
                None,
            )
            fault, victim = car, other
            if not e.get("at_fault") and partner is not None and partner.get("at_fault"):
                fault, victim = other, car
            blamed = bool(e.get("at_fault")) or bool(partner and partner.get("at_fault"))
            text = f"{_name(names, fault)} hit {_name(names, victim)}"
            text += f" ({_name(names, fault)} at fault)" if blamed else " (nobody at fault)"
            out.append(
                TimelineEvent(t=t, type=kind, car=fault, other=victim, at_fault=blamed, text=text)
            )
        elif kind == "off_track":
            out.append(TimelineEvent(t=t, type=kind, car=car, text=f"{who} off track"))
        elif kind == "finish":
            out.append(TimelineEvent(t=t, type=kind, car=car, text=f"{who} finished"))
        elif kind == "dnf":
            reason = e.get("reason") or "unknown"
            out.append(TimelineEvent(t=t, type=kind, car=car, text=f"{who} out: dnf ({reason})"))
    return out


def penalties(events: Sequence[Mapping[str, Any]], *, ranked: bool) -> dict[str, list[Penalty]]:
    """Each car's penalties with their reasons (empty in unranked races)."""
    out: dict[str, list[Penalty]] = {}
    if not ranked:
        return out
    for e in sorted(events, key=lambda e: float(e.get("t", 0.0))):
        t, car = float(e.get("t", 0.0)), str(e.get("car", ""))
        if e.get("type") == "off_track":
            item = Penalty(
                t=t, seconds=PENALTY_SECONDS["off_track"], reason=f"off track at {t:.1f} s"
            )
        elif e.get("type") == "collision" and e.get("at_fault"):
            item = Penalty(
                t=t,
                seconds=PENALTY_SECONDS["collision"],
                reason=f"collision with {e.get('other')} (at fault) at {t:.1f} s",
            )
        else:
            continue
        out.setdefault(car, []).append(item)
    return out


__all__ = ["Penalty", "TimelineEvent", "penalties", "timeline"]
