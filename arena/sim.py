"""The pybullet world: a track's road and walls, and 1/10-scale Ackermann cars.

Arrays in, arrays out; no pettingzoo, no gymnasium. Each :class:`Simulator` owns its own
pybullet ``DIRECT`` client, so many live in one process.

The car is a single rigid box (0.5 m × 0.3 m × 0.12 m, 3 kg) whose contacts with walls and
other cars are solved by pybullet. The road itself is frictionless for the chassis: the four
tyres are modelled here and applied as one force and one yaw torque per physics substep. That
is the "equivalent" of a jointed car the design allows, and it is what makes a car cheap to
step (no joints, no motors, one body):

* Ackermann steering: the front wheels get individual angles so that both point at the same
  turning centre (the inner wheel steers more), ``tan δ_in = L tan δ / (L − (t/2) tan δ)``.
* Each tyre pushes against its own lateral slip velocity with a gain that would cancel it in
  about one substep (a stiff, always-stable tyre), saturating at the friction circle
  ``|F| ≤ μ N``. Below the limit the car follows the kinematic bicycle (turn radius
  ``L / tan δ``); above it, it slides.
* A DC-motor drive on all four wheels: ``F = u · m · a_drive · (1 − v / v_max)`` forward,
  a constant braking deceleration for negative throttle while rolling forward, and a slower
  reverse gear once stopped. Rolling resistance is a small constant deceleration.

Default rates: physics at 60 Hz (``dt ≈ 17 ms``: a car at top speed moves 12 cm per substep,
less than half its width and the wall thickness, so contacts do not tunnel) and control at
20 Hz (3 substeps; a decision every 50 ms, between DeepRacer's 15 Hz and a servo's
response). The tyre model is written per substep so it stays stable at any rate; 100 Hz
physics changes pursuit lap times by under 0.5% and turn radii by 2%, at 1.6× the cost.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import tempfile
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from arena.colours import car_colour
from arena.walls import DEFAULT_RUNOFF, Clearance, Walls
from tracks import Track
from tracks.errors import SlipstreamError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


def _import_pybullet() -> Any:
    """Import pybullet with its build banner (printed on stderr) silenced, so that the
    command line's output and one-line errors stay clean."""
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        import pybullet  # noqa: PLC0415 - imported here to silence its banner

        return pybullet
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


class _LazyPybullet:
    """Stands in for the pybullet module until it is first used, then replaces itself.

    Importing :mod:`arena` (the package, its version and colours) must stay light: the
    leaderboard's web process reads them and never loads pybullet.
    """

    def __getattr__(self, name: str) -> Any:
        global pb  # noqa: PLW0603 - the module global is the cache
        if isinstance(pb, _LazyPybullet):  # a caller holding the proxy must not re-import
            pb = _import_pybullet()
        return getattr(pb, name)


pb: Any = _LazyPybullet()

GRAVITY = 9.81  # m/s²
WALL_THICKNESS = 0.2  # m
WALL_HEIGHT = 0.3  # m
PARKING_X = 1.0e4  # m: where cars that left the race wait, far from any track
MAX_COMPOUND_SHAPES = 16  # pybullet's limit on shapes per create*ShapeArray call
TILT_INERTIA = 1.0e4  # kg m²: a car's roll and pitch inertia, so the box stays flat
# m kept between what may touch, for skipping pybullet's contact query: far beyond the
# distance within which it keeps contact points (0.02 m breaking threshold, scaled by a
# shape's size).
CONTACT_MARGIN = 0.25
CLEARANCE_CELL = 0.25  # m: cells of the wall-clearance grid behind that skip
CLEARANCE_CAP = 1.25  # m: the largest clearance kept (a car at 7 m/s needs 0.92 m at 20 Hz)


# Attributes that name the pybullet connection: never copied (a copy connects its own).
_WORLD_HANDLES = frozenset({"client"})


class SimError(SlipstreamError):
    """The simulator was configured wrongly (bad rates, car count, parameters)."""


@dataclass(frozen=True)
class CarParams:
    """Physical parameters of the 1/10-scale car; frozen so that they can be randomised."""

    length: float = 0.5  # m, chassis box
    width: float = 0.3  # m
    height: float = 0.12  # m
    mass: float = 3.0  # kg
    wheelbase: float = 0.33  # m, front to rear axle
    track_width: float = 0.26  # m, left to right wheel
    max_steer: float = 0.42  # rad, at the road wheels (centre-line equivalent)
    steer_rate: float = 6.0  # rad/s, servo slew rate
    max_speed: float = 7.0  # m/s, motor no-load speed forward
    max_reverse_speed: float = 2.0  # m/s
    drive_accel: float = 6.0  # m/s² at standstill, full throttle
    brake_accel: float = 8.0  # m/s², full brake
    rolling_resistance: float = 0.1  # m/s²
    friction: float = 1.0  # tyre–road friction coefficient μ
    tyre_gain: float = 0.8  # fraction of a wheel's lateral slip cancelled per substep

    @property
    def top_speed(self) -> float:
        """Steady-state speed at full throttle on the flat, m/s."""
        return self.max_speed * (1.0 - self.rolling_resistance / self.drive_accel)

    def time_to_speed(self, fraction: float) -> float:
        """Seconds from rest at full throttle to ``fraction`` of the top speed (no slip)."""
        tau = self.max_speed / self.drive_accel
        return -tau * float(np.log(1.0 - fraction))


@dataclass
class CarScales:
    """Per-car multipliers and offsets on :class:`CarParams`, each (n_cars,).

    The model-uncertainty options set these; nominal is all ones and zero offset.
    """

    friction: FloatArray
    mass: FloatArray
    motor: FloatArray
    steer_gain: FloatArray
    steer_offset: FloatArray  # rad

    @classmethod
    def nominal(cls, n_cars: int) -> CarScales:
        """All cars at their nominal parameters."""
        one = np.ones(n_cars)
        return cls(one.copy(), one.copy(), one.copy(), one.copy(), np.zeros(n_cars))


@dataclass
class SimState:
    """What one control step produced, per car.

    Attributes:
        poses: (n, 3) [x m, y m, yaw rad].
        velocity: (n, 3) [vx m/s, vy m/s (world frame), yaw rate rad/s].
        v_long: (n,) forward speed in the car frame, m/s (negative when reversing).
        v_lat: (n,) leftward speed in the car frame, m/s.
        steering: (n,) current road-wheel steering angle, rad (positive turns left).
        upright: (n,) z of the car's up axis (1 upright, below 0.3 means flipped).
        wall_contact: (n,) True when the car touched a wall during the step.
        car_contact: (n, n) True where cars i and j touched during the step (symmetric).
        time: simulated seconds since reset.
    """

    poses: FloatArray
    velocity: FloatArray
    v_long: FloatArray
    v_lat: FloatArray
    steering: FloatArray
    upright: FloatArray
    wall_contact: BoolArray
    car_contact: BoolArray
    time: float = 0.0
    extras: dict[str, FloatArray] = field(default_factory=dict)


def ackermann_angles(steer: float, wheelbase: float, track_width: float) -> tuple[float, float]:
    """Front-wheel angles (left, right) rad for a centre-line steering angle rad (+ left).

    Both wheels point at the turning centre on the rear axle line, so the inner wheel steers
    more: ``tan δ_left = L tan δ / (L − (t/2) tan δ)``.
    """
    tan = math.tan(steer)
    half = 0.5 * track_width
    return (
        math.atan(wheelbase * tan / (wheelbase - half * tan)),
        math.atan(wheelbase * tan / (wheelbase + half * tan)),
    )


def car_corners(poses: FloatArray, length: float, width: float) -> FloatArray:
    """Corners (n, 4, 2) m of car rectangles at poses (n, 3) [x, y, yaw].

    Order: front-left, rear-left, rear-right, front-right (counter-clockwise).
    """
    lx, ly = _corner_offsets(length, width)
    trig = np.empty((len(poses), 1, 2))  # [cos, sin] of each yaw
    np.cos(poses[:, 2], out=trig[:, 0, 0])
    np.sin(poses[:, 2], out=trig[:, 0, 1])
    # x + cos·lx − sin·ly and y + sin·lx + cos·ly for both coordinates at once: the second
    # products are [sin, cos] times [−ly, ly] (a sign flip is exact; a + (−b) is a − b).
    return (poses[:, None, :2] + trig * lx) + trig[..., ::-1] * ly


@functools.lru_cache(maxsize=16)
def _corner_offsets(length: float, width: float) -> tuple[FloatArray, FloatArray]:
    """(4, 1) and (4, 2) m: the corners' x in the car frame, and their y as [−y, y], in
    :func:`car_corners`' order."""
    hl, hw = 0.5 * length, 0.5 * width
    lx, ly = np.array([[hl], [-hl], [-hl], [hl]]), np.array([hw, hw, -hw, -hw])
    ly_pair = np.stack([-ly, ly], axis=1)
    lx.flags.writeable = ly_pair.flags.writeable = False
    return lx, ly_pair


def drive_force(throttle: float, v_long: float, p: CarParams, motor: float, mass: float) -> float:
    """Longitudinal drive/brake force, N, for a throttle in [-1, 1] at forward speed m/s.

    Forward: a DC motor, ``u · a_drive · gain · (1 − v / v_max)``. Negative throttle brakes at
    ``u · a_brake`` while rolling forward faster than 0.3 m/s, then drives in reverse up to
    ``max_reverse_speed``. Those accelerations are the nominal car's (``p.mass``): the motor
    and the brakes give the same force whatever the car weighs, so a car ``k`` times as heavy
    (``mass`` = ``k · p.mass``) gets ``1/k`` of them. Rolling resistance (an acceleration)
    opposes motion, its force in proportion to ``mass``.
    """
    if throttle >= 0.0:
        force = throttle * p.drive_accel * motor * (1.0 - v_long / p.max_speed)
    elif v_long > 0.3:
        force = throttle * p.brake_accel
    else:
        force = min(throttle * p.drive_accel * motor * (1.0 + v_long / p.max_reverse_speed), 0.0)
    return p.mass * force - mass * p.rolling_resistance * math.tanh(v_long / 0.05)


class Simulator:
    """pybullet world with one track and ``n_cars`` cars.

    Args:
        track: the track whose road and walls to build.
        n_cars: number of cars (1–16).
        params: nominal car parameters.
        physics_hz: physics substep rate, Hz.
        control_hz: control rate, Hz; ``physics_hz`` must be a multiple of it.
        runoff: metres between the road edge and the walls.
        visuals: also build visual shapes (road, walls, coloured cars) for :meth:`camera`;
            costs nothing per step, a little at reset.

    Move the cars through these methods (:meth:`reset`, :meth:`step`, :meth:`park`): a step
    starts from the state the previous one read. After changing a body with pybullet
    directly, call :meth:`sync`.
    """

    def __init__(
        self,
        track: Track,
        n_cars: int,
        *,
        params: CarParams | None = None,
        physics_hz: int = 60,
        control_hz: int = 20,
        runoff: float = DEFAULT_RUNOFF,
        visuals: bool = False,
    ) -> None:
        if not 1 <= n_cars <= 16:
            raise SimError(f"n_cars must be between 1 and 16, got {n_cars}")
        if control_hz <= 0 or physics_hz <= 0 or physics_hz % control_hz:
            raise SimError(
                f"physics_hz ({physics_hz}) must be a positive multiple of control_hz "
                f"({control_hz})"
            )
        self.track = track
        self.n_cars = n_cars
        self.params = params or CarParams()
        self.physics_hz = physics_hz
        self.control_hz = control_hz
        self.substeps = physics_hz // control_hz
        self.dt = 1.0 / physics_hz
        self.visuals = visuals
        self.wall_lines = Walls.around(track, runoff)
        self.client = pb.connect(pb.DIRECT)
        self.scales = CarScales.nominal(n_cars)
        self.steering = np.zeros(n_cars)
        self.substeps_done = 0
        # The cars' state as last read (see _read), while no body has moved since.
        self._last_read: list[tuple[float, ...]] | None = None
        # Per car: (steering rad, its front wheels' (y offset m, cos, sin of the wheel angle),
        # left then right), recomputed when the steering changes.
        half = 0.5 * self.params.track_width
        straight = (0.0, ((half, 1.0, 0.0), (-half, 1.0, 0.0)))
        self._wheel_angles: list[tuple[Any, ...]] = [straight] * n_cars
        # The wall boxes (built once), and the clearance grid around them (on first use).
        self._boxes: tuple[FloatArray, FloatArray, FloatArray] | None = None
        self._clearance: Clearance | None = None
        self._build_world()

    # ---- world construction ---------------------------------------------------------------

    def _build_world(self) -> None:
        self._last_read = None  # new bodies
        c = self.client
        pb.resetSimulation(physicsClientId=c)
        pb.setGravity(0, 0, -GRAVITY, physicsClientId=c)
        pb.setPhysicsEngineParameter(
            fixedTimeStep=self.dt, numSolverIterations=10, physicsClientId=c
        )
        plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=c)
        self.ground = pb.createMultiBody(0, plane, physicsClientId=c)
        pb.changeDynamics(self.ground, -1, lateralFriction=0.0, physicsClientId=c)
        self.walls = self._build_walls()
        self._wall_bodies = frozenset(self.walls)
        p = self.params
        box = pb.createCollisionShape(
            pb.GEOM_BOX,
            halfExtents=[p.length / 2, p.width / 2, p.height / 2],
            physicsClientId=c,
        )
        self.cars: list[int] = []
        for k in range(self.n_cars):
            look = -1
            if self.visuals:
                look = pb.createVisualShape(
                    pb.GEOM_BOX,
                    halfExtents=[p.length / 2, p.width / 2, p.height / 2],
                    rgbaColor=[*(ch / 255 for ch in car_colour(k)), 1.0],
                    physicsClientId=c,
                )
            body = pb.createMultiBody(
                p.mass, box, look, basePosition=[0.0, 2.0 * k, p.height / 2], physicsClientId=c
            )
            pb.changeDynamics(
                body,
                -1,
                lateralFriction=0.3,
                restitution=0.1,
                linearDamping=0.0,
                angularDamping=0.0,
                physicsClientId=c,
            )
            self._set_mass(body, p.mass)
            self.cars.append(body)
        self._body_index = {b: i for i, b in enumerate(self.cars)}

    def _build_walls(self) -> list[int]:
        """Static bodies of boxes whose inner faces follow :class:`Walls`.

        pybullet keeps at most ``MAX_COMPOUND_SHAPES`` shapes of a ``create*ShapeArray`` call
        (the rest are silently dropped, and ``rgbaColors`` beyond that crashes it), so the
        boxes go into one compound body per run of that many consecutive wall segments.
        """
        centres, halves, yaws = self._wall_boxes()
        half_extents = [[float(a), float(b), WALL_HEIGHT / 2] for a, b in halves]
        positions = [[float(x), float(y), WALL_HEIGHT / 2] for x, y in centres]
        orientations = [pb.getQuaternionFromEuler([0.0, 0.0, float(a)]) for a in yaws]
        if self.visuals:
            self._build_road_visual()
        bodies = []
        for lo in range(0, len(half_extents), MAX_COMPOUND_SHAPES):
            part = slice(lo, lo + MAX_COMPOUND_SHAPES)
            count = len(half_extents[part])
            shape = pb.createCollisionShapeArray(
                [pb.GEOM_BOX] * count,
                halfExtents=half_extents[part],
                collisionFramePositions=positions[part],
                collisionFrameOrientations=orientations[part],
                physicsClientId=self.client,
            )
            visual = -1
            if self.visuals:
                visual = pb.createVisualShapeArray(
                    [pb.GEOM_BOX] * count,
                    halfExtents=half_extents[part],
                    visualFramePositions=positions[part],
                    visualFrameOrientations=orientations[part],
                    physicsClientId=self.client,
                )
            body = pb.createMultiBody(0, shape, visual, physicsClientId=self.client)
            pb.changeDynamics(
                body, -1, lateralFriction=0.2, restitution=0.2, physicsClientId=self.client
            )
            if self.visuals:
                pb.changeVisualShape(
                    body, -1, rgbaColor=[0.92, 0.92, 0.92, 1.0], physicsClientId=self.client
                )
            bodies.append(int(body))
        return bodies

    def _build_road_visual(self) -> None:
        """A dark road surface over a green ground, so the camera sees the road edges."""
        c, t = self.client, self.track
        ground = pb.createVisualShape(
            pb.GEOM_BOX,
            halfExtents=[500, 500, 0.001],
            rgbaColor=[0.36, 0.5, 0.33, 1],
            physicsClientId=c,
        )
        pb.createMultiBody(0, -1, ground, basePosition=[0, 0, -0.001], physicsClientId=c)
        n = t.n_points
        verts = np.empty((2 * n, 3))
        verts[0::2, :2], verts[1::2, :2] = t.left_border, t.right_border
        verts[:, 2] = 0.002
        k = 2 * np.arange(n)
        k1 = (k + 2) % (2 * n)
        tris = np.stack([k, k + 1, k1, k + 1, k1 + 1, k1], axis=1).reshape(-1, 3)
        tris = np.vstack([tris, tris[:, ::-1]])  # both faces, whatever the orientation
        road = pb.createVisualShape(
            pb.GEOM_MESH,
            vertices=verts.tolist(),
            indices=tris.ravel().tolist(),
            rgbaColor=[0.27, 0.27, 0.29, 1],
            physicsClientId=c,
        )
        pb.createMultiBody(0, -1, road, physicsClientId=c)

    def camera(self, i: int, width: int = 160, height: int = 120) -> NDArray[np.uint8]:
        """Grayscale ego-camera image (height, width, 1) uint8 from car ``i`` (120° wide).

        Needs ``visuals=True``. Rendered with pybullet's software TinyRenderer (headless).
        """
        if not self.visuals:
            raise SimError("the camera needs Simulator(visuals=True)")
        (x, y, z), quat = pb.getBasePositionAndOrientation(
            self.cars[i], physicsClientId=self.client
        )
        yaw = float(_yaw(np.asarray([quat]))[0])
        fwd = np.array([math.cos(yaw), math.sin(yaw)])
        eye = [x + 0.2 * fwd[0], y + 0.2 * fwd[1], z + 0.12]
        target = [x + 2.0 * fwd[0], y + 2.0 * fwd[1], 0.0]
        view = pb.computeViewMatrix(eye, target, [0, 0, 1], physicsClientId=self.client)
        vfov = math.degrees(2 * math.atan(math.tan(math.radians(60)) * height / width))
        proj = pb.computeProjectionMatrixFOV(
            vfov, width / height, 0.05, 30.0, physicsClientId=self.client
        )
        _, _, rgba, _, _ = pb.getCameraImage(
            width,
            height,
            view,
            proj,
            renderer=pb.ER_TINY_RENDERER,
            physicsClientId=self.client,
        )
        rgb = np.asarray(rgba, dtype=np.float32).reshape(height, width, 4)[..., :3]
        gray = rgb @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
        return np.clip(gray, 0, 255).astype(np.uint8)[..., None]

    # ---- parameters -----------------------------------------------------------------------

    def set_scales(self, scales: CarScales) -> None:
        """Apply per-car parameter multipliers (mass changes the pybullet body too)."""
        for name in ("friction", "mass", "motor", "steer_gain", "steer_offset"):
            if np.shape(getattr(scales, name)) != (self.n_cars,):
                raise SimError(f"CarScales.{name} must have shape ({self.n_cars},)")
        if not np.array_equal(scales.mass, self.scales.mass):
            self._last_read = None
            for body, m in zip(self.cars, scales.mass, strict=True):
                self._set_mass(body, float(self.params.mass * m))
        self.scales = scales

    def _set_mass(self, body: int, mass: float) -> None:
        """Give car ``body`` a mass, kg, with its box's yaw inertia and locked roll and pitch.

        The tyres act in the plane, so the car must stay flat: a box sliding on pybullet's
        frictionless ground plane otherwise rocks and sinks into it (the plane contact keeps
        too few manifold points once the box moves) and a car driving straight slowly yaws.
        pybullet recomputes the inertia on every mass change, hence both calls here.
        """
        p = self.params
        pb.changeDynamics(body, -1, mass=mass, physicsClientId=self.client)
        yaw_inertia = mass * (p.length**2 + p.width**2) / 12.0
        pb.changeDynamics(
            body,
            -1,
            localInertiaDiagonal=[TILT_INERTIA, TILT_INERTIA, yaw_inertia],
            physicsClientId=self.client,
        )

    # ---- state ----------------------------------------------------------------------------

    def reset(self, poses: FloatArray) -> SimState:
        """Place cars at rest at ``poses`` (n, 3) [x m, y m, yaw rad] and return the state."""
        poses = np.asarray(poses, dtype=np.float64)
        if poses.shape != (self.n_cars, 3):
            raise SimError(f"poses must have shape ({self.n_cars}, 3), got {poses.shape}")
        # A fresh world every episode: no solver caches or contact manifolds carry over, so
        # the same seed and actions give the same trajectory however many resets came before.
        self._build_world()
        kept = self.scales  # the new bodies have nominal mass: re-apply the scales
        self.scales = CarScales.nominal(self.n_cars)
        self.set_scales(kept)
        z = self.params.height / 2
        for body, (x, y, yaw) in zip(self.cars, poses, strict=True):
            pb.resetBasePositionAndOrientation(
                body,
                [x, y, z],
                pb.getQuaternionFromEuler([0.0, 0.0, yaw]),
                physicsClientId=self.client,
            )
            pb.resetBaseVelocity(body, [0, 0, 0], [0, 0, 0], physicsClientId=self.client)
        self.steering = np.zeros(self.n_cars)
        self.substeps_done = 0
        return self._observe(np.zeros(self.n_cars, bool), np.zeros((self.n_cars,) * 2, bool))

    def _read(self) -> list[tuple[float, ...]]:
        """Per car, [x, y, z, quaternion x, y, z, w, vx, vy, vz, wx, wy, wz] (13 floats)."""
        c, get_pose, get_vel = self.client, pb.getBasePositionAndOrientation, pb.getBaseVelocity
        rows = []
        for body in self.cars:
            pos, quat = get_pose(body, c)
            lin, ang = get_vel(body, c)
            rows.append(pos + quat + lin + ang)
        self._last_read = rows
        return rows

    def _observe(self, wall: BoolArray, cars: BoolArray) -> SimState:
        # Arithmetic per car in Python floats (the values numpy gives, without its per-call
        # overhead on a few cars); the angle functions stay numpy's, on arrays.
        rows = self._read()
        yaw_y, yaw_x = [], []
        for row in rows:
            qx, qy, qz, qw = row[3:7]
            yaw_y.append(2.0 * (qw * qz + qx * qy))
            yaw_x.append(1.0 - 2.0 * (qy * qy + qz * qz))
        parts = np.array([yaw_y, yaw_x])
        yaw = np.arctan2(parts[0], parts[1])  # as _yaw
        # One array (n, 9) holds every per-car field: the state's arrays are views into it
        # (one conversion from Python floats instead of one per field).
        cols = []
        for row, a, cos, sin in zip(
            rows, yaw.tolist(), np.cos(yaw).tolist(), np.sin(yaw).tolist(), strict=True
        ):
            qx, qy, vx, vy = row[3], row[4], row[7], row[8]
            v_long, v_lat = cos * vx + sin * vy, -sin * vx + cos * vy
            upright = 1.0 - 2.0 * (qx * qx + qy * qy)
            cols.append((row[0], row[1], a, vx, vy, row[12], v_long, v_lat, upright))
        table = np.array(cols)
        return SimState(
            poses=table[:, 0:3],
            velocity=table[:, 3:6],
            v_long=table[:, 6],
            v_lat=table[:, 7],
            steering=self.steering.copy(),
            upright=table[:, 8],
            wall_contact=wall,
            car_contact=cars,
            time=self.time,
        )

    # ---- stepping -------------------------------------------------------------------------

    def step(self, steer_cmd: FloatArray, throttle: FloatArray) -> SimState:
        """Advance one control step.

        Args:
            steer_cmd: (n,) steering command in [-1, 1] (fraction of ``max_steer``, +left).
            throttle: (n,) in [-1, 1]; negative brakes, then reverses once stopped.

        Returns:
            The state after ``substeps`` physics steps, with contacts seen during any of them.
        """
        p = self.params
        s = self.scales
        # In Python floats per car: np.clip's numbers (NaN stays NaN: min and max return
        # their first argument unless the other compares beyond it) without numpy's
        # per-call overhead on a few cars.
        target = []
        for u, gain, offset in zip(
            _floats(steer_cmd), s.steer_gain.tolist(), s.steer_offset.tolist(), strict=True
        ):
            angle = min(max(u, -1.0), 1.0) * p.max_steer * gain + offset
            target.append(min(max(angle, -p.max_steer), p.max_steer))
        tyres = self._tyre_constants([min(max(u, -1.0), 1.0) for u in _floats(throttle)])
        wall = np.zeros(self.n_cars, dtype=bool)
        touching = np.zeros((self.n_cars, self.n_cars), dtype=bool)
        max_delta, low = p.steer_rate * self.dt, -p.steer_rate * self.dt
        # The servo in Python floats: the numbers numpy's clip gives, without its overhead.
        steering = self.steering.tolist()
        step, client = pb.stepSimulation, self.client
        # The first substep starts from the state the last step (or reset) read.
        rows, self._last_read = self._last_read, None
        # pybullet's contact query is the dearest call of a substep: skipped when no car can
        # reach a wall or another car before the step ends (the same flags: none).
        apart = rows is not None and self._kept_apart(rows, tyres)
        for _ in range(self.substeps):
            steering = [
                now + min(max(goal - now, low), max_delta)
                for now, goal in zip(steering, target, strict=True)
            ]
            self._apply_tyre_forces(steering, tyres, rows)
            rows = None
            step(client)
            self.substeps_done += 1
            if not apart:
                self._collect_contacts(wall, touching)
        self.steering = np.array(steering, dtype=np.float64)
        return self._observe(wall, touching)

    def _kept_apart(self, rows: list[tuple[float, ...]], tyres: list[tuple[Any, ...]]) -> bool:
        """True when no car can touch a wall or another car during this control step.

        Without a contact the only horizontal force on a car is its tyres' (the ground is
        frictionless for the chassis), at most four wheels at the friction limit: its centre
        moves at most ``|v| T + a T²`` in the step's T seconds (semi-implicit Euler over the
        substeps), from the state ``rows`` read at its start. Each car's footprint, a circle
        of the chassis' half-diagonal grown by that much, must stay ``CONTACT_MARGIN`` from
        every wall box (:class:`arena.walls.Clearance`) and from every other footprint: far
        beyond the distance at which pybullet keeps a contact point. Then its contact query
        would report no car-wall or car-car point, and is not needed.

        Args:
            rows: per car, the state :meth:`_read` read at the step's start.
            tyres: per car, from :meth:`_tyre_constants` (mass, friction limit per wheel).
        """
        if self._clearance is None:
            boxes = self._wall_boxes()
            self._clearance = Clearance.of_boxes(*boxes, CLEARANCE_CELL, CLEARANCE_CAP)
        clearance, period = self._clearance, self.substeps * self.dt
        p = self.params
        radius = math.hypot(0.5 * p.length, 0.5 * p.width)
        spots: list[tuple[float, float, float]] = []
        for row, (_, _, _, mass, _, limit) in zip(rows, tyres, strict=True):
            x, y = row[0], row[1]
            accel = 4.0 * limit / mass  # m/s²: all four tyres at their friction limit
            reach = radius + period * math.hypot(row[7], row[8]) + accel * period * period
            if not reach + CONTACT_MARGIN < clearance.at(x, y):  # NaN: not apart
                return False
            for xo, yo, ro in spots:
                if not reach + ro + CONTACT_MARGIN < math.hypot(x - xo, y - yo):
                    return False
            spots.append((x, y, reach))
        return True

    def _wall_boxes(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The wall boxes (centres, half-extents, yaws) of :meth:`Walls.boxes`, built once."""
        if self._boxes is None:
            self._boxes = self.wall_lines.boxes(WALL_THICKNESS, self.track)
        return self._boxes

    def _tyre_constants(self, throttles: list[float]) -> list[tuple[Any, ...]]:
        """Per car, what its tyre forces need that stays fixed over one control step:
        (body, throttle, motor gain, mass kg, lateral gain N s/m, friction limit N)."""
        p, sc = self.params, self.scales
        gain = p.tyre_gain / self.dt
        out = []
        for body, throttle, mass_scale, motor, grip in zip(
            self.cars,
            throttles,
            sc.mass.tolist(),
            sc.motor.tolist(),
            sc.friction.tolist(),
            strict=True,
        ):
            mass = p.mass * mass_scale
            limit = 0.25 * p.friction * grip * mass * GRAVITY
            out.append((body, throttle, motor, mass, -gain * (0.25 * mass), limit))
        return out

    def _apply_tyre_forces(
        self,
        steering: list[float],
        tyres: list[tuple[Any, ...]],
        rows: list[tuple[float, ...]] | None = None,
    ) -> None:
        """Compute and apply each car's tyre forces for one substep.

        Scalar math per car, inside the loop that already calls pybullet per car: for up to
        16 cars that is several times cheaper than numpy on 4-element arrays. The four wheels
        are written out (the rear ones do not steer: cos 0 = 1 and sin 0 = 0 drop out
        exactly), in the same order of operations as one loop over the wheels would take.
        pybullet's arguments go by position (keywords cost a parse per call).

        Args:
            steering: (n,) road-wheel angles, rad, this substep.
            tyres: per car, from :meth:`_tyre_constants`.
            rows: per car, the state as :meth:`_read` read it (position, quaternion, linear
                and angular velocity), if nothing moved the bodies since; None: query it.
        """
        p, c = self.params, self.client
        wheelbase, half = p.wheelbase, 0.5 * p.track_width
        lf = lr = 0.5 * wheelbase
        get_pose, get_vel = pb.getBasePositionAndOrientation, pb.getBaseVelocity
        force, torque_of, frame = pb.applyExternalForce, pb.applyExternalTorque, pb.WORLD_FRAME
        cos, sin, hypot, atan2, copysign = math.cos, math.sin, math.hypot, math.atan2, math.copysign
        wheels = self._wheel_angles
        rear = (half, -half)
        for i, (body, throttle, motor, mass, k_lat, limit) in enumerate(tyres):
            if rows is None:
                pos, (qx, qy, qz, qw) = get_pose(body, c)
                (vxw, vyw, _), (_, _, r) = get_vel(body, c)
            else:
                row = rows[i]
                pos, (qx, qy, qz, qw), vxw, vyw, r = row[0:3], row[3:7], row[7], row[8], row[12]
            yaw = atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
            cy, sy = cos(yaw), sin(yaw)
            vx = cy * vxw + sy * vyw
            vy = -sy * vxw + cy * vyw
            steer = steering[i]
            cached = wheels[i]
            # The servo holds its angle once there: the same angle gives the same wheels
            # (compared bit for bit, so -0.0 and 0.0 are not mixed up).
            if cached[0] != steer or (
                steer == 0.0 and copysign(1.0, cached[0]) != copysign(1.0, steer)
            ):
                d_left, d_right = ackermann_angles(steer, wheelbase, p.track_width)
                front = ((half, cos(d_left), sin(d_left)), (-half, cos(d_right), sin(d_right)))
                cached = (steer, front)
                wheels[i] = cached
            f_drive = 0.25 * drive_force(throttle, vx, p, motor, mass)
            # Front wheels (steered), then rear wheels: ux = vx − r·wy, uy = vy + r·wx.
            fx_b = fy_b = torque = 0.0
            uy = vy + r * lf  # both front wheels
            for wy, cd, sd in cached[1]:  # (wy m, cos, sin of the wheel angle) left, right
                ux = vx - r * wy
                f_lat = k_lat * (-sd * ux + cd * uy)
                f_long = f_drive
                norm = hypot(f_long, f_lat)
                if norm > limit:  # friction circle: the tyre slides
                    f_long *= limit / norm
                    f_lat *= limit / norm
                fx = cd * f_long - sd * f_lat
                fy = sd * f_long + cd * f_lat
                fx_b += fx
                fy_b += fy
                torque += lf * fy - wy * fx
            # The rear wheels do not steer: both have the same slip, so the same forces
            # (computed once, still added wheel by wheel in the same order).
            f_lat = k_lat * (vy + r * -lr)
            f_long = f_drive
            norm = hypot(f_long, f_lat)
            if norm > limit:
                f_long *= limit / norm
                f_lat *= limit / norm
            yaw_lat = -lr * f_lat
            for wy in rear:
                fx_b += f_long
                fy_b += f_lat
                torque += yaw_lat - wy * f_long
            force(body, -1, (cy * fx_b - sy * fy_b, sy * fx_b + cy * fy_b, 0.0), pos, frame, c)
            torque_of(body, -1, (0.0, 0.0, torque), frame, c)

    def _collect_contacts(self, wall: BoolArray, touching: BoolArray) -> None:
        """OR this substep's car–wall and car–car contacts into the given arrays."""
        index, walls = self._body_index, self._wall_bodies
        for contact in pb.getContactPoints(physicsClientId=self.client):
            a, b = contact[1], contact[2]
            ia, ib = index.get(a), index.get(b)
            if ia is not None and ib is not None:
                touching[ia, ib] = touching[ib, ia] = True
            elif ia is not None and b in walls:
                wall[ia] = True
            elif ib is not None and a in walls:
                wall[ib] = True

    @property
    def time(self) -> float:
        """Simulated seconds since reset (counted in substeps, so no rounding drift)."""
        return self.substeps_done / self.physics_hz

    def sync(self) -> None:
        """Forget the cars' state read at the end of the last step.

        :meth:`step` starts from that state instead of querying pybullet again (each query
        copies pybullet's whole state record, about 30 KB: a quarter of the queries a step
        made). Call this after changing a car's body with pybullet directly (a test giving
        a car a velocity); the simulator's own methods keep it right by themselves.
        """
        self._last_read = None

    def park(self, i: int) -> None:
        """Take car ``i`` out of the race: moved far off the track and stopped."""
        self._last_read = None
        pb.resetBasePositionAndOrientation(
            self.cars[i],
            [PARKING_X + 5.0 * i, PARKING_X, self.params.height / 2],
            [0, 0, 0, 1],
            physicsClientId=self.client,
        )
        pb.resetBaseVelocity(self.cars[i], [0, 0, 0], [0, 0, 0], physicsClientId=self.client)
        self.steering[i] = 0.0

    def corners(self, poses: FloatArray) -> FloatArray:
        """(n, 4, 2) m: rectangle corners [front-left, rear-left, rear-right, front-right]."""
        return car_corners(poses, self.params.length, self.params.width)

    def close(self) -> None:
        """Disconnect the pybullet client (idempotent)."""
        if self.client >= 0:
            pb.disconnect(physicsClientId=self.client)
            self.client = -1

    def __del__(self) -> None:
        with contextlib.suppress(Exception):  # at interpreter exit pybullet may be gone
            self.close()

    # ---- copies ---------------------------------------------------------------------------

    def __getstate__(self) -> dict[str, Any]:
        """Everything but the pybullet client: the bodies' poses and velocities by value.

        ``copy.deepcopy`` and pickle (cloudpickle, multiprocessing "spawn") use this, so a
        copy never shares its physics with the original.
        """
        out = {k: v for k, v in self.__dict__.items() if k not in _WORLD_HANDLES}
        out["_bodies"] = None
        if self.client >= 0:
            # pybullet's own snapshot of the dynamics world (exact transforms and
            # velocities; reading poses back through the API rounds them).
            with tempfile.TemporaryDirectory() as tmp:
                path = os.path.join(tmp, "world.bullet")
                pb.saveBullet(path, physicsClientId=self.client)
                with open(path, "rb") as fh:
                    out["_bodies"] = fh.read()
        return out

    def __setstate__(self, state: dict[str, Any]) -> None:
        """Connect a fresh pybullet client, rebuild the world and restore every body."""
        bodies = state.pop("_bodies")
        self.__dict__.update(state)
        self.client = -1
        if bodies is None:  # a closed simulator stays closed
            return
        self.client = pb.connect(pb.DIRECT)
        self._build_world()
        kept = self.scales  # the new bodies have nominal mass: re-apply the scales
        self.scales = CarScales.nominal(self.n_cars)
        self.set_scales(kept)
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "world.bullet")
            with open(path, "wb") as fh:
                fh.write(bodies)
            pb.restoreState(fileName=path, physicsClientId=self.client)


def _floats(x: Any) -> list[float]:
    """(n,) numbers as a list of Python floats (float64 values)."""
    out: list[float] = np.asarray(x, dtype=np.float64).tolist()
    return out


def _yaw(quat: FloatArray) -> FloatArray:
    """Yaw angle (n,) rad of quaternions (n, 4) [x, y, z, w]."""
    x, y, z, w = quat[:, 0], quat[:, 1], quat[:, 2], quat[:, 3]
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
