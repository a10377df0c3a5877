"""Action modes: continuous ``[steer, throttle]`` or a DeepRacer-style discrete grid.

Continuous: a Box ``[-1, 1]²``. ``steer`` is the fraction of full lock (+ turns left);
``throttle`` drives forward when positive; when negative it brakes while rolling forward and
then drives in reverse.

Discrete: ``Discrete(n_steer × n_speed)``. Action ``i`` selects steering
``linspace(-1, 1, n_steer)[i % n_steer]`` and target speed
``linspace(0, top_speed, n_speed + 1)[1 + i // n_steer]`` m/s; a proportional speed
controller turns the target into a throttle (``(target − v) / 1 m/s``, clipped to [-1, 1]).
DeepRacer's default menu is 5 steering angles × 2 speeds = 10 actions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

SPEED_GAIN = 1.0  # throttle per m/s of speed error in the discrete controller


@dataclass(frozen=True)
class DiscreteActions:
    """A steering × speed menu.

    Attributes:
        n_steer: steering values, evenly spaced over [-1, 1] (odd keeps "straight ahead").
        n_speed: target speeds, evenly spaced over (0, top_speed].
        top_speed: fastest target, m/s.
    """

    n_steer: int = 5
    n_speed: int = 2
    top_speed: float = 6.8

    def __post_init__(self) -> None:
        if self.n_steer < 1 or self.n_speed < 1:
            raise ValueError("a discrete action grid needs at least one steering and one speed")

    @property
    def n(self) -> int:
        """Number of actions."""
        return self.n_steer * self.n_speed

    def menu(self) -> FloatArray:
        """(n, 2) [steer in [-1, 1], target speed m/s] of every action."""
        steer = np.linspace(-1.0, 1.0, self.n_steer) if self.n_steer > 1 else np.zeros(1)
        speed = np.linspace(0.0, self.top_speed, self.n_speed + 1)[1:]
        return np.stack([np.tile(steer, self.n_speed), np.repeat(speed, self.n_steer)], axis=1)

    def to_controls(
        self, actions: NDArray[np.int64], v_long: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Steering commands and throttles (n,) for action indices (n,) at speeds (n,) m/s."""
        chosen = self.menu()[np.clip(actions, 0, self.n - 1)]
        throttle = np.clip(SPEED_GAIN * (chosen[:, 1] - v_long), -1.0, 1.0)
        return chosen[:, 0], throttle
