"""``backend="batch"``: a vectorised simulator of the same cars on the same tracks.

Brax's lesson: thousands of environments stepped together with uniform, branch-free array
math train far faster than one simulator per process. :class:`arena.batch.sim.BatchSim`
steps ``B`` environments × ``N`` cars at once with the same car model as the pybullet
:class:`arena.sim.Simulator` (single-track Ackermann car, DC motor, friction-circle tyres),
soft box contacts between cars, walls through a signed-distance grid and a lidar read from a
precomputed range table — numpy on the CPU or torch on a GPU through one code path
(:mod:`arena.batch.xp`). On top of it:

* :class:`arena.batch.vec_env.BatchVecEnv`: a stable-baselines3 ``VecEnv`` whose batch is
  every car of every environment;
* :class:`arena.batch.parallel.BatchParallelEnv`: the PettingZoo ``ParallelEnv`` for
  ``B = 1`` (``arena.parallel_env(backend="batch")``).

How close it is to pybullet (tests/arena/test_batch_parity.py):

* driving without contact: the same tyre model integrated the same way (semi-implicit Euler),
  positions within 0.1 mm of pybullet over 2 s (stated bound 1 cm); pure-pursuit lap times
  identical (to the 0.05 s step) on every built-in track;
* contacts: soft springs instead of pybullet's hard constraints — the same geometry
  (corner clearance within 4 mm of pybullet's contact distance), but a car can sink a few
  centimetres into a wall or another car; after a 4 m/s rear-end impact the two cars stay
  within 0.5 m of their pybullet paths over 2 s (measured 0.24 m);
* lidar: walls from a range table (median error 2 cm, 90% within 10 cm of the exact caster),
  other cars exact but only within the 16 rays around their bearing;
* track projection: onto the nearest centre-line segment (pybullet env: an
  interpolated-normal frame), the same to a few millimetres.

Speed (bench/batch_speed.py, 4 cars, 64-ray lidar, 2 vCPU AMD EPYC): about 200,000
agent-steps/s with numpy and 285,000 with torch on the CPU at 4,096 environments.

Names are imported lazily, so ``import arena.batch`` costs nothing.
"""

from __future__ import annotations

from typing import Any

_EXPORTS = {
    "BatchSim": "arena.batch.sim",
    "BatchVecEnv": "arena.batch.vec_env",
    "BatchParallelEnv": "arena.batch.parallel",
    "TrackMaps": "arena.batch.maps",
    "get_ops": "arena.batch.xp",
}


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        import importlib  # noqa: PLC0415 - lazy exports

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'arena.batch' has no attribute {name!r}")


__all__ = ["BatchParallelEnv", "BatchSim", "BatchVecEnv", "TrackMaps", "get_ops"]
