"""The car model of :mod:`arena.sim`, vectorised over any leading axes (``(B, N)``).

The same single-track Ackermann car as the pybullet simulator, term for term: servo slew
on the steering, Ackermann angles of the two front wheels, a DC-motor drive with braking and
a reverse gear (:func:`drive_accel`), and four tyres that each push against their own slip
velocity up to the friction circle ``|F| ≤ μ N/4``. What pybullet adds — integrating the
force and torque — is semi-implicit Euler here, as Bullet does it (velocities first, then
positions with the new velocities), so from the same state with the same commands the two
backends follow the same path up to round-off while no contact acts.

All functions are branch-free: ``where``/``minimum`` instead of per-car ``if``.
"""

from __future__ import annotations

from dataclasses import dataclass

from arena.batch.xp import Array, NumpyOps
from arena.sim import GRAVITY, CarParams


@dataclass
class CarState:
    """Rigid-body state of every car, each array (..., N).

    Attributes:
        x, y: position, m.
        yaw: heading, rad (not wrapped).
        vx, vy: world-frame velocity, m/s.
        r: yaw rate, rad/s.
        steering: road-wheel angle, rad (+ left).
    """

    x: Array
    y: Array
    yaw: Array
    vx: Array
    vy: Array
    r: Array
    steering: Array


@dataclass
class Scales:
    """Per-car multipliers on :class:`CarParams` (..., N), as :class:`arena.sim.CarScales`."""

    friction: Array
    mass: Array
    motor: Array
    steer_gain: Array
    steer_offset: Array  # rad


def steer_target(cmd: Array, p: CarParams, sc: Scales, ops: NumpyOps) -> Array:
    """Road-wheel target angle, rad, for steering commands in [-1, 1]."""
    raw = ops.clip(cmd, -1.0, 1.0) * p.max_steer * sc.steer_gain + sc.steer_offset
    return ops.clip(raw, -p.max_steer, p.max_steer)


def drive_accel(
    throttle: Array, v_long: Array, p: CarParams, motor: Array, mass_scale: Array, ops: NumpyOps
) -> Array:
    """Longitudinal drive/brake acceleration, m/s² (:func:`arena.sim.drive_force` / mass).

    ``mass_scale`` is the car's mass over the nominal one: the motor's and the brakes' forces are
    the nominal car's, so their accelerations are divided by it; rolling resistance is not.
    """
    forward = throttle * p.drive_accel * motor * (1.0 - v_long / p.max_speed)
    brake = throttle * p.brake_accel
    reverse = ops.minimum(
        throttle * p.drive_accel * motor * (1.0 + v_long / p.max_reverse_speed), 0.0
    )
    acc = ops.where(throttle >= 0.0, forward, ops.where(v_long > 0.3, brake, reverse))
    return acc / mass_scale - p.rolling_resistance * ops.tanh(v_long / 0.05)


def tyre_forces(
    st: CarState, throttle: Array, p: CarParams, sc: Scales, dt: float, ops: NumpyOps
) -> tuple[Array, Array, Array]:
    """World-frame tyre force (Fx, Fy) N and yaw torque N m on every car for one substep."""
    cy, sy = ops.cos(st.yaw), ops.sin(st.yaw)
    vx = cy * st.vx + sy * st.vy  # car frame
    vy = -sy * st.vx + cy * st.vy
    mass = p.mass * sc.mass
    f_drive = 0.25 * mass * drive_accel(throttle, vx, p, sc.motor, sc.mass, ops)
    wheel_mass = 0.25 * mass
    limit = 0.25 * p.friction * sc.friction * mass * GRAVITY
    gain = p.tyre_gain / dt
    lf = lr = 0.5 * p.wheelbase
    half = 0.5 * p.track_width
    # Ackermann: tan δ_left/right = L tan δ / (L ∓ (t/2) tan δ); cos and sin from the tangent.
    tan = ops.sin(st.steering) / ops.cos(st.steering)
    fx_b = fy_b = torque = 0.0
    for wx, wy, side in ((lf, half, 1.0), (lf, -half, -1.0), (-lr, half, 0.0), (-lr, -half, 0.0)):
        ux = vx - st.r * wy
        uy = vy + st.r * wx
        if side:  # front wheels steer (static: the same four wheels for every car)
            t_w = p.wheelbase * tan / (p.wheelbase - side * half * tan)
            cd = 1.0 / ops.sqrt(1.0 + t_w * t_w)
            sd = t_w * cd
            f_lat = -gain * wheel_mass * (-sd * ux + cd * uy)
        else:
            f_lat = -gain * wheel_mass * uy
        norm = ops.hypot(f_drive, f_lat)
        scale = ops.minimum(limit / ops.maximum(norm, 1e-12), 1.0)  # the friction circle
        f_long, f_lat = f_drive * scale, f_lat * scale
        if side:
            fx = cd * f_long - sd * f_lat
            fy = sd * f_long + cd * f_lat
        else:
            fx, fy = f_long, f_lat
        fx_b = fx_b + fx
        fy_b = fy_b + fy
        torque = torque + (wx * fy - wy * fx)
    return cy * fx_b - sy * fy_b, sy * fx_b + cy * fy_b, torque


def integrate(
    st: CarState,
    fx: Array,
    fy: Array,
    torque: Array,
    mass: Array,
    inertia: Array,
    dt: float,
    moving: Array,
) -> CarState:
    """Semi-implicit Euler: velocities from forces, then positions from the new velocities.

    ``moving`` (..., N) bool: cars that are out of the race stay where they are, at rest.
    """
    vx = (st.vx + fx / mass * dt) * moving
    vy = (st.vy + fy / mass * dt) * moving
    r = (st.r + torque / inertia * dt) * moving
    return CarState(
        x=st.x + vx * dt,
        y=st.y + vy * dt,
        yaw=st.yaw + r * dt,
        vx=vx,
        vy=vy,
        r=r,
        steering=st.steering,
    )
