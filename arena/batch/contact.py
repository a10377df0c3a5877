"""Contacts as soft forces: car against car (oriented boxes) and car against the walls.

pybullet solves contacts as hard constraints; the batched backend uses penalty forces, which
are uniform array math and need no contact lists. Each force is a damped spring on the
penetration depth, applied at the contact point (so it also turns the car), plus Coulomb
friction along the wall. The stiffnesses keep the spring period above three
substeps at 60 Hz, so explicit integration stays stable; the price is that a car hitting a
wall head-on at full speed sinks up to ~10 cm into it before it is pushed back out. The
wall damper is close to critical, as pybullet's walls (restitution 0.2) barely bounce.

* Car–car: oriented rectangles, overlap by separating axes; the least-overlap axis is the
  normal, the depth drives the spring, and the force and its reaction act on the two cars
  at the contact point.
* Car–wall: each corner's clearance from the walls comes from the track's signed-distance
  grid (bilinear), its direction from the grid's wall normal.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from arena.batch.dynamics import CarState
from arena.batch.xp import Array, NumpyOps


@dataclass(frozen=True)
class ContactParams:
    """Spring and damper constants of the soft contacts."""

    car_stiffness: float = 3000.0  # N/m of overlap between two cars
    car_damping: float = 60.0  # N s/m (fitted to pybullet rear-end impacts)
    wall_stiffness: float = 4000.0  # N/m per penetrating corner
    wall_damping: float = 120.0  # N s/m (close to critical: pybullet walls barely bounce)
    wall_friction: float = 0.2  # μ along the wall (pybullet's wall friction)


def corners(st: CarState, lx: Array, ly: Array, ops: NumpyOps) -> tuple[Array, Array, Array, Array]:
    """Corner positions (..., N, 4) x, y m and the car's cos, sin (..., N, 1).

    ``lx, ly`` (4,) m are the corners in the car frame, in the order of
    :func:`arena.sim.car_corners`: front-left, rear-left, rear-right, front-right.
    """
    cos, sin = ops.cos(st.yaw)[..., None], ops.sin(st.yaw)[..., None]
    x = st.x[..., None] + cos * lx - sin * ly
    y = st.y[..., None] + sin * lx + cos * ly
    return x, y, cos, sin


class PairMaps:
    """Constant matrices that gather car pairs and scatter their forces back, for N cars.

    Attributes:
        i, j: (P,) the unordered pairs i < j, P = N·(N−1)/2.
        push: (P, N) +1 at i, −1 at j: a pair force on i and its reaction on j.
        on_i, on_j: (P, N) one-hot of i and of j.
        touch: (P, N·N) ones at (i, j) and (j, i).
    """

    def __init__(self, n: int, ops: NumpyOps) -> None:
        i, j = np.triu_indices(n, k=1)
        p = len(i)
        on_i, on_j = np.zeros((p, n)), np.zeros((p, n))
        on_i[np.arange(p), i] = 1.0
        on_j[np.arange(p), j] = 1.0
        touch = np.zeros((p, n * n))
        touch[np.arange(p), i * n + j] = 1.0
        touch[np.arange(p), j * n + i] = 1.0
        self.n = n
        self.i, self.j = ops.asarray(i.astype(np.int64)), ops.asarray(j.astype(np.int64))
        self.push = ops.asarray(on_i - on_j)
        self.on_i, self.on_j = ops.asarray(on_i), ops.asarray(on_j)
        self.touch = ops.asarray(touch)


def car_contacts(
    st: CarState,
    cos: Array,
    sin: Array,
    active: Array,
    half_length: float,
    half_width: float,
    cp: ContactParams,
    pm: PairMaps,
    ops: NumpyOps,
) -> tuple[Array, Array, Array, Array]:
    """Forces (Fx, Fy) N and torques N m (..., N) of all car–car contacts, and who touches.

    Separating axes: two rectangles overlap when their projections overlap on all four of
    their axes; the axis of least overlap gives the contact normal and the penetration
    depth. The force acts at the midpoint of the two rectangles' support points along the
    normal (with a soft sign, so two aligned bumpers meet in their middles, not at a corner).

    Args:
        st: the cars' state.
        cos, sin: (..., N) of each car's yaw.
        active: (..., N) cars still racing (others touch nothing).
        half_length, half_width: of the car's rectangle, m.
        cp: contact constants.
        pm: the pair matrices for N cars.
        ops: array namespace.

    Returns:
        fx, fy, torque (..., N) and touching (..., N, N) bool (symmetric).
    """
    i, j = pm.i, pm.j
    hl, hw = half_length, half_width
    ci, si, cj, sj = cos[..., i], sin[..., i], cos[..., j], sin[..., j]
    dx, dy = st.x[..., i] - st.x[..., j], st.y[..., i] - st.y[..., j]  # from j to i
    ac = ops.abs(ci * cj + si * sj)  # |cos(yaw_i − yaw_j)|
    as_ = ops.abs(si * cj - ci * sj)
    reach_u = hl + hl * ac + hw * as_  # both rectangles' half-extents along a long axis
    reach_v = hw + hl * as_ + hw * ac  # ... along a short axis
    d_ui, d_vi = ci * dx + si * dy, ci * dy - si * dx
    d_uj, d_vj = cj * dx + sj * dy, cj * dy - sj * dx
    o_ui, o_vi = reach_u - ops.abs(d_ui), reach_v - ops.abs(d_vi)
    o_uj, o_vj = reach_u - ops.abs(d_uj), reach_v - ops.abs(d_vj)
    depth_i = ops.minimum(o_ui, o_vi)
    depth_j = ops.minimum(o_uj, o_vj)
    depth = ops.minimum(depth_i, depth_j)
    inside = (depth > 0.0) & active[..., i] & active[..., j]
    # The normal: the least-overlap axis, pointing from j to i.
    use_i = depth_i <= depth_j
    long_i, long_j = o_ui <= o_vi, o_uj <= o_vj
    ax = ops.where(use_i, ops.where(long_i, ci, -si), ops.where(long_j, cj, -sj))
    ay = ops.where(use_i, ops.where(long_i, si, ci), ops.where(long_j, sj, cj))
    side = ops.where(ax * dx + ay * dy >= 0.0, 1.0, -1.0)
    nx, ny = ax * side, ay * side

    def soft_sign(v: Array) -> Array:
        return ops.clip(v * 20.0, -1.0, 1.0)  # ±1 beyond 0.05, linear across aligned faces

    # Support points: i's towards j (−n), j's towards i (+n); the force acts between them.
    a_i, b_i = soft_sign(ci * nx + si * ny), soft_sign(ci * ny - si * nx)
    a_j, b_j = soft_sign(cj * nx + sj * ny), soft_sign(cj * ny - sj * nx)
    pix = -hl * a_i * ci + hw * b_i * si  # relative to i's centre
    piy = -hl * a_i * si - hw * b_i * ci
    pjx = hl * a_j * cj - hw * b_j * sj  # relative to j's centre
    pjy = hl * a_j * sj + hw * b_j * cj
    rix, riy = 0.5 * (pix + pjx - dx), 0.5 * (piy + pjy - dy)  # contact point from i
    rjx, rjy = rix + dx, riy + dy  # ... and from j
    ri, rj = st.r[..., i], st.r[..., j]
    dvx = st.vx[..., i] - ri * riy - (st.vx[..., j] - rj * rjy)
    dvy = st.vy[..., i] + ri * rix - (st.vy[..., j] + rj * rjx)
    v_n = dvx * nx + dvy * ny
    f_n = ops.where(inside, ops.maximum(cp.car_stiffness * depth - cp.car_damping * v_n, 0.0), 0.0)
    fx, fy = f_n * nx, f_n * ny  # on i; the reaction −(fx, fy) acts on j at the same point
    t_i = rix * fy - riy * fx
    t_j = -(rjx * fy - rjy * fx)
    hit = ops.cast(inside, fx.dtype)
    touching = (ops.matmul(hit, pm.touch) > 0.0).reshape(*tuple(st.x.shape), pm.n)
    return (
        ops.matmul(fx, pm.push),
        ops.matmul(fy, pm.push),
        ops.matmul(t_i, pm.on_i) + ops.matmul(t_j, pm.on_j),
        touching,
    )


def wall_contacts(
    st: CarState,
    cx: Array,
    cy: Array,
    clearance: Array,
    normal_x: Array,
    normal_y: Array,
    active: Array,
    cp: ContactParams,
    ops: NumpyOps,
) -> tuple[Array, Array, Array, Array]:
    """Forces (Fx, Fy) N and torques N m (..., N) from the walls, and who touches one.

    Args:
        st: the cars' state.
        cx, cy: (..., N, 4) corner positions.
        clearance: (..., N, 4) m from each corner to the walls (negative: inside a wall).
        normal_x, normal_y: (..., N, 4) unit normal pointing away from the nearer wall.
        active: (..., N) cars still racing.
    """
    pen = ops.where(active[..., None], -clearance, 0.0)
    inside = pen > 0.0
    rx, ry = cx - st.x[..., None], cy - st.y[..., None]
    vx = st.vx[..., None] - st.r[..., None] * ry
    vy = st.vy[..., None] + st.r[..., None] * rx
    v_n = vx * normal_x + vy * normal_y
    f_n = ops.where(inside, ops.maximum(cp.wall_stiffness * pen - cp.wall_damping * v_n, 0.0), 0.0)
    # Friction along the wall, smoothed near zero slip so it cannot chatter.
    v_tx, v_ty = vx - v_n * normal_x, vy - v_n * normal_y
    v_t = ops.sqrt(v_tx * v_tx + v_ty * v_ty + 1e-6)
    f_t = cp.wall_friction * f_n * ops.tanh(v_t / 0.05) / v_t
    fx = f_n * normal_x - f_t * v_tx
    fy = f_n * normal_y - f_t * v_ty
    torque = rx * fy - ry * fx
    return (
        ops.sum(fx, axis=-1),
        ops.sum(fy, axis=-1),
        ops.sum(torque, axis=-1),
        ops.any(inside, axis=-1),
    )
