"""The ``cvar`` arm: PPO updates on the worst share of each rollout (:mod:`agents.cvar`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from gymnasium import spaces

from agents.cvar import CVAR_SHARE, CVAR_WARMUP, WorstShareRolloutBuffer, cvar_buffer

N_STEPS, N_ENVS = 4, 6


def filled(share: float, warmup: int, rewards: np.ndarray) -> WorstShareRolloutBuffer:
    """A buffer of ``N_STEPS × N_ENVS`` with ``rewards`` (n_steps, n_envs) and each row's
    observation holding its (slot, step), so a sample says where it came from."""
    buffer = WorstShareRolloutBuffer(
        N_STEPS,
        spaces.Box(-np.inf, np.inf, (2,), np.float32),
        spaces.Box(-1.0, 1.0, (2,), np.float32),
        device="cpu",
        n_envs=N_ENVS,
        share=share,
        warmup_rollouts=warmup,
    )
    refill(buffer, rewards)
    return buffer


def refill(buffer: WorstShareRolloutBuffer, rewards: np.ndarray) -> None:
    import torch

    buffer.reset()
    for t in range(N_STEPS):
        obs = np.array([[e, t] for e in range(N_ENVS)], np.float32)
        buffer.add(
            obs,
            np.zeros((N_ENVS, 2), np.float32),
            rewards[t],
            np.zeros(N_ENVS, bool),
            torch.zeros(N_ENVS),
            torch.zeros(N_ENVS),
        )
    buffer.compute_returns_and_advantage(torch.zeros(N_ENVS), np.zeros(N_ENVS, bool))


def drawn(buffer: WorstShareRolloutBuffer, batch_size: int) -> list[tuple[int, int]]:
    """The (slot, step) of every row one epoch of minibatches yields, in order."""
    rows = []
    for batch in buffer.get(batch_size):
        assert len(batch.observations) <= batch_size
        rows += [(int(e), int(t)) for e, t in batch.observations.numpy()]
    return rows


def test_after_the_warm_up_an_update_draws_only_the_worst_slots_every_step_of_them() -> None:
    # slot returns over the rollout: 3, -4, 0, -1, 5, -4 (a tie at -4: the lower index wins)
    per_step = np.array([3, -4, 0, -1, 5, -4], np.float32) / N_STEPS
    rewards = np.tile(per_step, (N_STEPS, 1))
    buffer = filled(share=0.5, warmup=1, rewards=rewards)
    first = drawn(buffer, batch_size=5)  # the warm-up rollout: every slot
    assert sorted(first) == [(e, t) for e in range(N_ENVS) for t in range(N_STEPS)]
    assert buffer.kept.tolist() == list(range(N_ENVS))
    refill(buffer, rewards)
    epoch = drawn(buffer, batch_size=5)
    assert buffer.kept.tolist() == [1, 3, 5]  # the worst half: -4, -4, -1
    assert sorted(epoch) == [(e, t) for e in (1, 3, 5) for t in range(N_STEPS)]
    again = drawn(buffer, batch_size=5)  # a second epoch: the same rows, reshuffled
    assert sorted(again) == sorted(epoch)
    # the samples carry their own row's data: advantages and returns of the kept slots
    batch = next(buffer.get(None))
    slots = batch.observations[:, 0].numpy().astype(int)
    assert set(slots) == {1, 3, 5}
    assert np.allclose(batch.returns.numpy(), batch.advantages.numpy())  # values were 0


def test_the_worst_share_follows_each_rollout_and_keeps_at_least_one_slot() -> None:
    rewards = np.tile(np.arange(N_ENVS, dtype=np.float32), (N_STEPS, 1))
    buffer = filled(share=0.01, warmup=0, rewards=rewards)
    drawn(buffer, 64)
    assert buffer.kept.tolist() == [0]
    refill(buffer, -rewards)  # the order turned round: now the last slot is the worst
    drawn(buffer, 64)
    assert buffer.kept.tolist() == [N_ENVS - 1]
    whole = filled(share=1.0, warmup=0, rewards=rewards)
    drawn(whole, 64)
    assert whole.kept.tolist() == list(range(N_ENVS))


@pytest.mark.parametrize("share", [0.0, -0.5, 1.5])
def test_a_share_outside_zero_to_one_is_refused(share: float) -> None:
    with pytest.raises(ValueError, match="share"):
        filled(share=share, warmup=0, rewards=np.zeros((N_STEPS, N_ENVS), np.float32))


def test_the_arm_s_warm_up_is_its_share_of_the_budget() -> None:
    kwargs = cvar_buffer(total_timesteps=1_000_000, n_steps=64, n_envs=100)
    assert kwargs["rollout_buffer_class"] is WorstShareRolloutBuffer
    assert kwargs["rollout_buffer_kwargs"] == {
        "share": CVAR_SHARE,
        "warmup_rollouts": int(CVAR_WARMUP * 1_000_000 / 6400),
    }


@pytest.mark.slow
def test_train_the_cvar_arm_on_the_batch_backend(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The arm as the experiment trains it: wide randomisation, the worst half per update.
    from agents.robustness import training_uncertainty
    from agents.train import TrainArgs, main

    kept: list[tuple[int, int]] = []  # (slots kept, slots) per update
    real = WorstShareRolloutBuffer.select

    def spy(self: WorstShareRolloutBuffer) -> np.ndarray:
        out = real(self)
        kept.append((len(out), self.n_envs))
        return out

    monkeypatch.setattr(WorstShareRolloutBuffer, "select", spy)

    args = TrainArgs(
        backend="batch",
        tracks=["oval"],
        eval_tracks=["oval"],
        n_cars=2,
        n_envs=4,
        total_timesteps=2048,
        n_steps=64,
        batch_size=128,
        n_epochs=1,
        eval_every=0,
        save_best=False,
        uncertainty="cvar",
        out=tmp_path,
        run_name="cvar",
        progress_bar=False,
    )
    summary = main(args)
    assert summary["training"]["steps"] >= 2048
    assert (tmp_path / "cvar" / "policy.zip").is_file()
    assert training_uncertainty("cvar") == training_uncertainty("wide")
    # every rollout of 64 steps × its slots (no warm-up at this budget): each update on half
    slots = kept[0][1]
    assert slots > 1 and kept == [(slots // 2, slots)] * -(-2048 // (64 * slots)), kept


def test_the_share_is_the_one_asked_for_and_a_share_outside_zero_to_one_is_refused() -> None:
    from agents.policy import PolicyError
    from agents.train import TrainArgs, _check

    kwargs = cvar_buffer(total_timesteps=64_000, n_steps=64, n_envs=10, share=0.75)
    assert kwargs["rollout_buffer_kwargs"]["share"] == 0.75
    assert cvar_buffer(64_000, 64, 10, warmup=0.0)["rollout_buffer_kwargs"]["warmup_rollouts"] == 0
    assert cvar_buffer(64_000, 64, 10, warmup=0.5)["rollout_buffer_kwargs"]["warmup_rollouts"] == 50
    _check(TrainArgs(uncertainty="cvar", cvar_share=1.0, cvar_warmup=0.0))
    for bad in (0.0, 1.5):
        with pytest.raises(PolicyError, match="cvar_share"):
            _check(TrainArgs(uncertainty="cvar", cvar_share=bad))
    for bad in (-0.1, 1.0):
        with pytest.raises(PolicyError, match="cvar_warmup"):
            _check(TrainArgs(uncertainty="cvar", cvar_warmup=bad))
