"""A curriculum on the bounds: domain randomisation that widens as training goes.

Issue 17 names it among the methods to try when plain domain randomisation does not buy
enough robustness. A policy trained from scratch over the whole randomisation set spends its
first updates on cars it cannot drive yet (a 0.4-friction car with three steps of latency
on a hairpin); with the curriculum it first learns on cars near the nominal one and meets
the harder ones once it drives. This is the schedule of progressive domain randomisation
(the bounds grow with the step count, as in OpenAI's automatic domain randomisation but
without its performance gate): at ``t`` agent-steps of a budget ``T`` the bounds are the
training set's scaled about the nominal car (:meth:`arena.uncertainty.UncertaintyConfig.scaled`)
by::

    s(t) = start + (1 − start) · min(1, t / (ramp · T))

so they start at ``start`` (:data:`CURRICULUM_START`) of their width, reach the full set at
``ramp`` of the budget and stay there. The scale changes at each rollout's end, for every
simulator of the batched vector env (:meth:`arena.batch.sim.BatchSim.set_uncertainty`);
each car keeps its perturbation until its next draw (the next episode). ``start`` keeps
every parameter of the set free (latency's whole steps included: 0–2 steps scaled by 0.3
round to 0–1, by 0.25 to 0–0), so the global state and any nature's action keep their
width.

``slipstream train --backend batch --uncertainty sample|wide|cvar --curriculum RAMP``.
"""

from __future__ import annotations

from typing import Any

CURRICULUM_START = 0.3  # the share of the bounds' width the curriculum starts from
CURRICULUM_ARMS = ("sample", "wide", "cvar")  # the domain-randomisation arms it widens


def curriculum_scale(done: int, total: int, ramp: float, start: float = CURRICULUM_START) -> float:
    """The bounds' scale after ``done`` of ``total`` agent-steps: ``start`` at 0, 1 from
    ``ramp · total`` on, linear between (see the module docstring); 1 with ``ramp`` 0."""
    if ramp <= 0.0:
        return 1.0
    return start + (1.0 - start) * min(1.0, done / (ramp * total))


def curriculum_callback(cfg: Any, vec_env: Any, total: int, ramp: float) -> Any:
    """An SB3 callback that sets every simulator of ``vec_env`` (a batched vector env, its
    ``sims``) to ``cfg`` scaled by :func:`curriculum_scale` at the start of training and at
    each rollout's end.

    Args:
        cfg: the full training set, an :class:`arena.uncertainty.UncertaintyConfig`.
        vec_env: :class:`arena.batch.vec_env.BatchVecEnv` (the procedural redraw copies the
            current bounds of the simulator it replaces).
        total: the budget, agent-steps.
        ramp: the share of the budget over which the bounds grow, in (0, 1].

    The callback's ``scales`` holds ``(agent-steps, scale)`` at each change.
    """
    from stable_baselines3.common.callbacks import BaseCallback  # noqa: PLC0415 - heavy

    class Curriculum(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.scales: list[tuple[int, float]] = []

        def _set(self) -> None:
            s = round(curriculum_scale(self.num_timesteps, total, ramp), 4)
            if self.scales and self.scales[-1][1] == s:
                return
            scaled = cfg.scaled(s)
            for sim in vec_env.sims:
                sim.set_uncertainty(scaled)
            self.scales.append((int(self.num_timesteps), s))

        def _on_training_start(self) -> None:
            self._set()

        def _on_step(self) -> bool:
            return True

        def _on_rollout_end(self) -> None:
            self._set()

    return Curriculum()
