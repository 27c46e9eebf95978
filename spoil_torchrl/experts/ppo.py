"""PPO and PPO-Lagrangian experts from TorchRL pieces, used to make demonstration data (paper F.2, Table G).

PPO-Lagrangian (Ray et al., 2019) adds a cost critic, a cost advantage (GAE on ``("next", "cost")``) and a
multiplier :math:`\\lambda \\ge 0` on the episode-cost limit :math:`d`: the policy maximises the surrogate of
:math:`(A_r - \\lambda A_c)/(1 + \\lambda)`, and after every batch :math:`\\lambda` takes one Adam step on
:math:`-\\lambda (\\bar C - d)` (then is clipped at 0), with :math:`\\bar C` the mean cost of the episodes
finished in the batch. The Adam step (OmniSafe's choice) moves :math:`\\lambda` by about ``lagrange_lr`` per
batch whatever the size of the violation; a plain gradient step with episode costs in the hundreds makes
:math:`\\lambda` explode (measured: 114 after 14 batches with rate 0.05) and the policy then ignores reward. With
``lagrangian=False`` it is plain PPO. Checkpoints (actor weights plus the batch's mean episode return and cost)
are written periodically, so the four policy types of the paper can be picked from them afterwards.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from tensordict import TensorDict
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers import SamplerWithoutReplacement
from torchrl.envs import TransformedEnv
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE
from tqdm.auto import tqdm

from spoil_torchrl.modules import make_actor, make_value_network


@dataclass
class PPOConfig:
    """Hyper-parameters of :func:`train_ppo` (defaults: common PPO settings for Safety-Gymnasium tasks)."""

    total_frames: int = 1_000_000
    frames_per_batch: int = 10_000
    epochs: int = 10
    minibatch_size: int = 1000
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_epsilon: float = 0.2
    actor_lr: float = 3e-4
    critic_lr: float = 1e-3
    entropy_coeff: float = 0.0
    max_grad_norm: float = 0.5
    hidden_cells: tuple[int, ...] = (64, 64)
    lagrangian: bool = False
    cost_limit: float = 25.0
    lagrange_lr: float = 0.035
    lagrange_init: float = 0.0
    checkpoint_every: int = 5  # batches
    seed: int = 0
    extra: dict = field(default_factory=dict)


class EpisodeTracker:
    """Undiscounted return and cost of the episodes that finish in successive batches of one environment."""

    def __init__(self) -> None:
        self.running = torch.zeros(2, dtype=torch.float64)

    def update(self, batch: TensorDict) -> tuple[float, float, int]:
        """Mean return and cost of the episodes finished in ``batch`` (NaN if none) and their number."""
        if batch.ndim != 1:
            raise ValueError(
                f"EpisodeTracker expects one environment's [T] batch, got batch size {batch.shape}"
            )
        steps = torch.cat([batch["next", "reward"], batch["next", "cost"]], -1).reshape(-1, 2).double()
        done = batch["next", "done"].reshape(-1)
        finished = []
        start = 0
        for end in (done.nonzero().squeeze(-1) + 1).tolist():
            finished.append(self.running + steps[start:end].sum(0))
            self.running = torch.zeros(2, dtype=torch.float64)
            start = end
        self.running = self.running + steps[start:].sum(0)
        if not finished:
            return math.nan, math.nan, 0
        totals = torch.stack(finished)
        return float(totals[:, 0].mean()), float(totals[:, 1].mean()), len(finished)


def train_ppo(
    make_env: Callable[[], TransformedEnv],
    observation_dim: int,
    action_dim: int,
    config: PPOConfig,
    out_dir: str | Path,
    *,
    progress: bool = True,
) -> list[dict]:
    """Train a PPO (or PPO-Lagrangian, ``config.lagrangian``) policy and checkpoint it under ``out_dir``.

    Args:
        make_env: builds the TorchRL environment (with ``("next", "cost")``), e.g.
            ``functools.partial(spoil_torchrl.envs.make_env, "SafetyPointCircle1-v0", seed=0)``.
        observation_dim, action_dim: sizes of the task.
        config: :class:`PPOConfig`.
        out_dir: checkpoints ``ckpt_<frames>.pt`` (the actor ``state_dict`` that collected that batch, with the
            batch's episode statistics; loadable with ``weights_only=True``)
            and ``log.jsonl`` (one line per batch: frames, mean episode return and cost, lambda, seconds).

    Returns:
        the log lines.
    """
    torch.manual_seed(config.seed)
    run_dir = Path(out_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps(asdict(config), indent=2))

    actor = make_actor(
        observation_dim,
        action_dim,
        hidden_cells=config.hidden_cells,
        distribution="tanh_normal",
        return_log_prob=True,
    )
    critic = make_value_network(
        observation_dim, hidden_cells=config.hidden_cells, out_key="state_value", activation_class=nn.Tanh
    )
    cost_critic = make_value_network(
        observation_dim, hidden_cells=config.hidden_cells, out_key="cost_value", activation_class=nn.Tanh
    )
    collector = Collector(
        make_env,
        actor,
        frames_per_batch=config.frames_per_batch,
        total_frames=config.total_frames,
        auto_register_policy_transforms=False,
    )
    collector.set_seed(config.seed)
    reward_gae = GAE(gamma=config.gamma, lmbda=config.gae_lambda, value_network=critic, average_gae=False)
    cost_gae = GAE(gamma=config.gamma, lmbda=config.gae_lambda, value_network=cost_critic, average_gae=False)
    cost_gae.set_keys(
        reward="cost", value="cost_value", advantage="cost_advantage", value_target="cost_value_target"
    )
    loss = ClipPPOLoss(
        actor,
        critic,
        clip_epsilon=config.clip_epsilon,
        entropy_coeff=config.entropy_coeff,
        loss_critic_type="l2",
        normalize_advantage=False,
    )
    optim = torch.optim.Adam(
        [
            {"params": loss.actor_network_params.values(True, True), "lr": config.actor_lr},
            {"params": loss.critic_network_params.values(True, True), "lr": config.critic_lr},
            {"params": cost_critic.parameters(), "lr": config.critic_lr},
        ]
    )
    buffer = TensorDictReplayBuffer(
        storage=LazyTensorStorage(config.frames_per_batch),
        sampler=SamplerWithoutReplacement(),
        batch_size=config.minibatch_size,
    )
    lagrange_param = nn.Parameter(torch.tensor(float(config.lagrange_init)))
    lagrange_optim = torch.optim.Adam([lagrange_param], lr=config.lagrange_lr)
    lagrange = config.lagrange_init
    log: list[dict] = []
    frames, start = 0, time.perf_counter()
    bar = tqdm(
        total=config.total_frames, desc="ppo-lag" if config.lagrangian else "ppo", disable=not progress
    )
    tracker = EpisodeTracker()
    for i, batch in enumerate(collector):
        frames += batch.numel()
        ep_return, ep_cost, n_episodes = tracker.update(batch)
        line = {
            "frames": frames,
            "episode_return": ep_return,
            "episode_cost": ep_cost,
            "episodes": n_episodes,
        }
        if (i + 1) % config.checkpoint_every == 0 or frames >= config.total_frames:
            # the weights that collected this batch, with that batch's episode statistics
            torch.save({"actor": actor.state_dict(), **line}, run_dir / f"ckpt_{frames:09d}.pt")
        with torch.no_grad():
            reward_gae(batch)
            cost_gae(batch)
        if config.lagrangian and n_episodes:  # no finished episode: no new cost estimate, no step
            lagrange_optim.zero_grad()
            (-lagrange_param * (ep_cost - config.cost_limit)).backward()
            lagrange_optim.step()
            with torch.no_grad():
                lagrange_param.clamp_(min=0.0)
            lagrange = float(lagrange_param.detach())
        advantage = batch["advantage"]
        if config.lagrangian:
            advantage = (advantage - lagrange * batch["cost_advantage"]) / (1.0 + lagrange)
        batch["advantage"] = (advantage - advantage.mean()) / (advantage.std() + 1e-8)
        buffer.empty()
        buffer.extend(batch.reshape(-1))
        for _ in range(config.epochs):
            for _ in range(config.frames_per_batch // config.minibatch_size):
                mb = buffer.sample()
                terms = loss(mb)
                cost_pred = cost_critic(mb.select("observation").clone())["cost_value"]
                cost_loss = (cost_pred - mb["cost_value_target"]).pow(2).mean()
                total = (
                    terms["loss_objective"]
                    + terms["loss_critic"]
                    + terms.get("loss_entropy", 0.0)
                    + cost_loss
                )
                optim.zero_grad()
                total.backward()
                for group in optim.param_groups:  # actor, critic and cost critic clipped separately
                    nn.utils.clip_grad_norm_(group["params"], config.max_grad_norm)
                optim.step()
        collector.update_policy_weights_()
        line.update(lagrange=lagrange, seconds=time.perf_counter() - start)
        log.append(line)
        with open(run_dir / "log.jsonl", "a") as f:
            f.write(json.dumps(line) + "\n")
        bar.update(batch.numel())
        bar.set_postfix(ret=f"{ep_return:.1f}", cost=f"{ep_cost:.1f}", lam=f"{lagrange:.2f}")
    bar.close()
    collector.shutdown()
    return log
