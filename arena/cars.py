"""Car presets: named :class:`~arena.sim.CarParams` for the cars Slipstream races.

========== ====================== ========= ========= ========== ============ =========
name       car                    size (m)  wheelbase max steer  top speed    full lock
========== ====================== ========= ========= ========== ============ =========
f1tenth    F1TENTH 1/10 (default) 0.50×0.30 0.33 m    0.42 rad   6.9 m/s      0.74 m
deepracer  AWS DeepRacer 1/18     0.26×0.19 0.164 m   30° (0.52) 3.9 m/s      0.28 m
========== ====================== ========= ========= ========== ============ =========

("full lock" is the centre-line turning radius ``wheelbase / tan(max_steer)``.)

``"f1tenth"`` is exactly ``CarParams()``, today's car.

``"deepracer"`` is the AWS DeepRacer (and DeepRacer Evo) car, "an 1/18th scale 4WD with monster
truck chassis and ackermann drive" (aws-deepracer/aws-deepracer, ``deepracer_description/
README.md``). Its figures come from:

* Geometry: the car's published URDF, aws-deepracer/aws-deepracer
  ``deepracer_description/models/xacro/urdf/deepracer_front_facing_camera_urdf.xacro``: front
  steering hinges at x = +0.0823 m and rear axle at x = −0.0817 m (wheelbase 0.164 m), wheels at
  y = ±0.081 m (track 0.162 m), wheel radius 0.03 m and width 0.025 m. The chassis box here
  (0.26 × 0.19 × 0.10 m) is the wheels' footprint (0.224 × 0.187 m) plus the shell's overhang;
  0.10 m is the camera mount's height. Mass: chassis 1.907 kg + four 0.042 kg wheels + two
  0.05 kg steering hinges ≈ 2.2 kg.
* Steering limit and speed range: the AWS DeepRacer Developer Guide's action space
  (https://docs.aws.amazon.com/deepracer/latest/developerguide/deepracer-how-it-works-action-space.html):
  steering angle −30° to 30°, speed 0.5 m/s to 4 m/s. ``max_speed`` (the motor's no-load speed)
  is 4 m/s, so the top speed on the flat is 3.9 m/s after rolling resistance.
* Not published, chosen to match the car's size: acceleration 4 m/s² (a 1/18 brushed motor
  reaches 4 m/s in about 2.5 s), braking 6 m/s², reverse 1 m/s. Tyre friction μ = 1.0 like the
  F1TENTH car: the DeepRacer Gazebo simulator's μ = 0.5 (``deepracer_collision.xacro``) is an
  ODE friction-pyramid coefficient and does not carry over to this tyre model.

>>> car_params("deepracer").wheelbase
0.164
>>> car_params("f1tenth") == CarParams()
True
"""

from __future__ import annotations

import math

from arena.sim import CarParams
from tracks.errors import SlipstreamError


class CarError(SlipstreamError):
    """An unknown car preset name, or a car given as something other than a name or CarParams."""


DEEPRACER = CarParams(
    length=0.26,
    width=0.19,
    height=0.10,
    mass=2.2,
    wheelbase=0.164,
    track_width=0.162,
    max_steer=math.radians(30.0),
    steer_rate=6.0,
    max_speed=4.0,
    max_reverse_speed=1.0,
    drive_accel=4.0,
    brake_accel=6.0,
    rolling_resistance=0.1,
    friction=1.0,
    tyre_gain=0.8,
)

CAR_PRESETS: dict[str, CarParams] = {"f1tenth": CarParams(), "deepracer": DEEPRACER}
"""Preset name to its :class:`CarParams` (names in the table above); the values are frozen."""

DEFAULT_CAR = "f1tenth"


def car_params(spec: str | CarParams) -> CarParams:
    """The :class:`CarParams` for a preset name, or ``spec`` itself if it already is one.

    Args:
        spec: a name of :data:`CAR_PRESETS` (case-insensitive, surrounding spaces ignored) or a
            :class:`CarParams`.

    Raises:
        CarError: ``spec`` names no preset, or is neither a string nor a CarParams.
    """
    if isinstance(spec, CarParams):
        return spec
    if not isinstance(spec, str):
        raise CarError(f"car must be a preset name or CarParams, got {type(spec).__name__}")
    key = spec.strip().lower()
    if key not in CAR_PRESETS:
        raise CarError(f"unknown car {spec!r}; choose one of: {', '.join(CAR_PRESETS)}")
    return CAR_PRESETS[key]


def car_name(params: CarParams) -> str | None:
    """The preset name whose parameters equal ``params``, or None for a custom car."""
    for name, preset in CAR_PRESETS.items():
        if preset == params:
            return name
    return None


__all__ = ["CAR_PRESETS", "DEEPRACER", "DEFAULT_CAR", "CarError", "car_name", "car_params"]
