"""CleanRL-style PPO in one file, in torch, on the batched simulator (every car is a sample).

The whole algorithm is in this file (CleanRL's ``ppo_continuous_action.py``, adapted): a
Gaussian MLP policy with a value head, GAE, clipped surrogate, value loss, entropy bonus.
The environment is :class:`arena.batch.BatchSim`: ``n_envs`` races × ``n_cars`` cars stepped
as arrays, numpy on the CPU or torch on a GPU (``--device cuda``: observations and actions
then never leave the device). Every car is driven by the one policy (parameter sharing,
self-play), so a batch holds ``n_envs × n_cars × num_steps`` transitions. A race restarts
(new random start placement and grid order) as soon as one of its cars is done.

    python examples/cleanrl_ppo_batch.py --total-timesteps 500000 --n-envs 256

Metrics (printed per iteration, returned by :func:`main`): ``charts/reward_per_step`` (mean
reward of the batch: metres of progress minus penalties), ``charts/episodic_return``
(mean return of the races that ended), ``losses/value_loss``, ``losses/policy_loss``,
``losses/entropy``, ``losses/approx_kl``, ``charts/SPS`` (agent-steps per second).
"""

from __future__ import annotations

import argparse
import dataclasses
import random
import time
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
import torch
from torch import nn
from torch.distributions.normal import Normal

from arena.batch import BatchSim

_T = TypeVar("_T")


def flag(default: _T, help: str) -> _T:
    """An :class:`Args` field; ``help`` is its ``--help`` text."""
    return dataclasses.field(default=default, metadata={"help": help})


@dataclass
class Args:
    """Command-line arguments (``--total-timesteps 8192`` etc.)."""

    seed: int = flag(1, "seeds python, numpy, torch and the simulator's start draws")
    torch_deterministic: bool = flag(True, "torch.backends.cudnn.deterministic")
    threads: int = flag(1, "torch CPU threads: one is fastest for networks this small")
    track: str = flag("oval", "built-in name, file or random:<seed>")
    device: str = flag("numpy", "simulator arrays: numpy, torch:cpu, cuda")
    n_envs: int = flag(16, "races stepped together")
    n_cars: int = flag(2, "cars per race, all driven by the policy")
    total_timesteps: int = flag(4096, "agent-steps (cars × control steps) in all")
    learning_rate: float = flag(3e-4, "Adam step size")
    num_steps: int = flag(64, "control steps per rollout")
    gamma: float = flag(0.99, "discount factor")
    gae_lambda: float = flag(0.95, "GAE lambda")
    num_minibatches: int = flag(4, "minibatches per rollout")
    update_epochs: int = flag(4, "passes over each rollout")
    clip_coef: float = flag(0.2, "PPO clip range")
    ent_coef: float = flag(0.0, "entropy bonus coefficient")
    vf_coef: float = flag(0.5, "value loss coefficient")
    max_grad_norm: float = flag(0.5, "gradient clipping norm")
    dnf_penalty: float = flag(10.0, "subtracted when a car retires (stuck, off the track)")


def parse_args(argv: list[str] | None = None) -> Args:
    """``--flag value`` for every :class:`Args` field."""
    parser = argparse.ArgumentParser(
        description=(__doc__ or "").splitlines()[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    for f in dataclasses.fields(Args):
        flag = "--" + f.name.replace("_", "-")
        if isinstance(f.default, bool):
            parser.add_argument(
                flag,
                action=argparse.BooleanOptionalAction,
                default=f.default,
                help=f.metadata["help"],
            )
        else:
            parser.add_argument(
                flag, type=type(f.default), default=f.default, help=f.metadata["help"]
            )
    return Args(**vars(parser.parse_args(argv)))


def layer_init(layer: nn.Linear, std: float = np.sqrt(2), bias_const: float = 0.0) -> nn.Linear:
    """Orthogonal weights, constant bias (CleanRL's initialisation)."""
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


class Agent(nn.Module):
    """Actor (Gaussian mean, state-independent log-std) and critic, 64-unit tanh MLPs."""

    def __init__(self, obs_size: int, act_size: int = 2) -> None:
        super().__init__()
        self.critic = nn.Sequential(
            layer_init(nn.Linear(obs_size, 64)),
            nn.Tanh(),
            layer_init(nn.Linear(64, 64)),
            nn.Tanh(),
            layer_init(nn.Linear(64, 1), std=1.0),
        )
        self.actor_mean = nn.Sequential(
            layer_init(nn.Linear(obs_size, 64)),
            nn.Tanh(),
            layer_init(nn.Linear(64, 64)),
            nn.Tanh(),
            layer_init(nn.Linear(64, act_size), std=0.01),
        )
        self.actor_logstd = nn.Parameter(torch.zeros(1, act_size))

    def get_value(self, x: torch.Tensor) -> torch.Tensor:
        """Values (batch,) of observations (batch, obs_size)."""
        return self.critic(x).squeeze(-1)

    def get_action_and_value(
        self, x: torch.Tensor, action: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Action (sampled unless given), its log-probability, the entropy and the value."""
        mean = self.actor_mean(x)
        probs = Normal(mean, self.actor_logstd.expand_as(mean).exp())
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action).sum(1), probs.entropy().sum(1), self.get_value(x)

    def act(self, obs: np.ndarray) -> np.ndarray:
        """The deterministic action (2,) [steer, throttle] in [-1, 1] for one observation."""
        with torch.no_grad():
            mean = self.actor_mean(torch.as_tensor(obs, dtype=torch.float32)[None])
        return mean[0].clamp(-1.0, 1.0).numpy()


def evaluate(agent: Agent, args: Args, steps: int = 200, n_envs: int = 4) -> float:
    """Mean reward per car and step of the deterministic policy on fixed starts (``seed``).

    The same races every call, so two calls compare two policies: metres of progress per
    step, minus the racing penalties (an untrained policy stands still: about 0).
    """
    sim = BatchSim(args.track, n_envs, args.n_cars, device="numpy", seed=args.seed)
    obs = sim.reset(seed=args.seed)
    total = 0.0
    with torch.no_grad():
        for _ in range(steps):
            x = torch.as_tensor(np.asarray(obs), dtype=torch.float32).reshape(-1, obs.shape[-1])
            mean = agent.actor_mean(x.to(next(agent.parameters()).device)).clamp(-1.0, 1.0)
            res = sim.step(mean.cpu().numpy().reshape(n_envs, args.n_cars, 2))
            obs = res.obs
            total += float(np.mean(res.reward))
    return total / steps


def main(args: Args) -> dict[str, Any]:
    """Train; returns the per-iteration metrics (``history``) and the trained ``agent``."""
    # ---- seeding: one block -----------------------------------------------------------------
    random.seed(args.seed)
    rng = np.random.default_rng(args.seed)  # minibatch shuffles
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    torch.set_num_threads(args.threads)
    run_name = f"slipstream_{args.track}__cleanrl_ppo_batch__{args.seed}__{int(time.time())}"

    sim = BatchSim(
        args.track, args.n_envs, args.n_cars, device=args.device, random_starts=True, seed=args.seed
    )
    on_torch = args.device != "numpy"
    device = torch.device(args.device.removeprefix("torch:") if on_torch else "cpu")
    n_slots = args.n_envs * args.n_cars
    obs_size = sim.layout.size
    batch_size = n_slots * args.num_steps
    minibatch_size = batch_size // args.num_minibatches
    num_iterations = max(1, args.total_timesteps // batch_size)

    agent = Agent(obs_size).to(device)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)

    def tensor(a: Any) -> torch.Tensor:
        return torch.as_tensor(a, device=device).to(torch.float32).reshape(n_slots, -1).squeeze(-1)

    eval_before = evaluate(agent, args)
    obs_buf = torch.zeros((args.num_steps, n_slots, obs_size), device=device)
    act_buf = torch.zeros((args.num_steps, n_slots, 2), device=device)
    logp_buf = torch.zeros((args.num_steps, n_slots), device=device)
    rew_buf = torch.zeros((args.num_steps, n_slots), device=device)
    done_buf = torch.zeros((args.num_steps, n_slots), device=device)
    val_buf = torch.zeros((args.num_steps, n_slots), device=device)

    next_obs = tensor(sim.reset(seed=args.seed)).reshape(n_slots, obs_size)
    next_done = torch.zeros(n_slots, device=device)
    returns_so_far = torch.zeros(n_slots, device=device)
    history: list[dict[str, float]] = []
    start = time.perf_counter()
    global_step = 0
    print(f"run {run_name}: {num_iterations} iterations of {batch_size} agent-steps")

    for iteration in range(1, num_iterations + 1):
        finished: list[float] = []
        for step in range(args.num_steps):
            global_step += n_slots
            obs_buf[step], done_buf[step] = next_obs, next_done
            with torch.no_grad():
                action, logprob, _, value = agent.get_action_and_value(next_obs)
            val_buf[step], act_buf[step], logp_buf[step] = value, action, logprob
            sim_action = action.clamp(-1.0, 1.0).reshape(args.n_envs, args.n_cars, 2)
            res = sim.step(sim_action if on_torch else sim_action.cpu().numpy())
            laps = tensor(res.laps_completed)
            retired = tensor(res.terminated).bool() & (laps < sim.laps)
            reward = tensor(res.reward) - args.dnf_penalty * retired.float()
            rew_buf[step] = reward
            # A race restarts when any of its cars is done: every car of it starts afresh.
            env_done = torch.as_tensor(res.env_done, device=device).bool()
            next_done = env_done.repeat_interleave(args.n_cars).float()
            next_obs = tensor(res.obs).reshape(n_slots, obs_size)
            returns_so_far += reward
            finished += returns_so_far[next_done.bool()].tolist()
            returns_so_far *= 1.0 - next_done

        # ---- GAE ------------------------------------------------------------------------------
        with torch.no_grad():
            next_value = agent.get_value(next_obs)
            advantages = torch.zeros_like(rew_buf)
            lastgaelam = torch.zeros(n_slots, device=device)
            for t in reversed(range(args.num_steps)):
                nonterminal = 1.0 - (next_done if t == args.num_steps - 1 else done_buf[t + 1])
                nextvalues = next_value if t == args.num_steps - 1 else val_buf[t + 1]
                delta = rew_buf[t] + args.gamma * nextvalues * nonterminal - val_buf[t]
                lastgaelam = delta + args.gamma * args.gae_lambda * nonterminal * lastgaelam
                advantages[t] = lastgaelam
            returns = advantages + val_buf

        b_obs, b_act = obs_buf.reshape(-1, obs_size), act_buf.reshape(-1, 2)
        b_logp, b_adv = logp_buf.reshape(-1), advantages.reshape(-1)
        b_ret = returns.reshape(-1)

        # ---- optimise the policy and value network ------------------------------------------
        b_inds = np.arange(batch_size)
        for _epoch in range(args.update_epochs):
            rng.shuffle(b_inds)
            for lo in range(0, batch_size, minibatch_size):
                mb = torch.as_tensor(b_inds[lo : lo + minibatch_size], device=device)
                _, newlogp, entropy, newvalue = agent.get_action_and_value(b_obs[mb], b_act[mb])
                logratio = newlogp - b_logp[mb]
                ratio = logratio.exp()
                with torch.no_grad():
                    approx_kl = ((ratio - 1) - logratio).mean()
                mb_adv = (b_adv[mb] - b_adv[mb].mean()) / (b_adv[mb].std() + 1e-8)
                pg_loss = torch.max(
                    -mb_adv * ratio,
                    -mb_adv * torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef),
                ).mean()
                v_loss = 0.5 * ((newvalue - b_ret[mb]) ** 2).mean()
                entropy_loss = entropy.mean()
                loss = pg_loss - args.ent_coef * entropy_loss + v_loss * args.vf_coef
                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                optimizer.step()

        row = {
            "global_step": float(global_step),
            "charts/reward_per_step": float(rew_buf.mean()),
            "charts/episodic_return": float(np.mean(finished)) if finished else float("nan"),
            "losses/value_loss": v_loss.item(),
            "losses/policy_loss": pg_loss.item(),
            "losses/entropy": entropy_loss.item(),
            "losses/approx_kl": approx_kl.item(),
            "charts/SPS": global_step / (time.perf_counter() - start),
        }
        history.append(row)
        print(
            f"iter {iteration}/{num_iterations} step {global_step} "
            f"reward/step {row['charts/reward_per_step']:.3f} "
            f"return {row['charts/episodic_return']:.2f} "
            f"value_loss {row['losses/value_loss']:.3f} SPS {row['charts/SPS']:.0f}"
        )
    eval_after = evaluate(agent, args)
    print(f"deterministic reward per step on fixed starts: {eval_before:.3f} -> {eval_after:.3f}")
    return {
        "run_name": run_name,
        "history": history,
        "eval/reward_per_step_before": eval_before,
        "eval/reward_per_step_after": eval_after,
        "agent": agent.cpu(),
    }


if __name__ == "__main__":
    main(parse_args())
