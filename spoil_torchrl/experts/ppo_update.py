"""One PPO / PPO-Lagrangian update of an expert: the networks, the optional running observation
standardisation, the multiplier, and the clipped-surrogate epochs over one batch (used by
:func:`~spoil_torchrl.experts.train_ppo`)."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers import SamplerWithoutReplacement
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from spoil_torchrl.divergence import check_finite
from spoil_torchrl.experts.ppo_config import PPOConfig
from spoil_torchrl.modules import make_actor, make_value_network
from spoil_torchrl.modules.normalization import STD_EPS, ObservationNormalizer, with_observation_norm


class PPOLearner(nn.Module):
    """The networks, their optimiser, the Lagrange multiplier and the observation statistics: the state a
    batch's update changes (and a resumed training restores)."""

    def __init__(self, observation_dim: int, action_dim: int, config: PPOConfig) -> None:
        super().__init__()
        cells = config.hidden_cells
        self.actor = make_actor(
            observation_dim, action_dim, hidden_cells=cells, distribution="tanh_normal", return_log_prob=True
        )
        self.critic = make_value_network(
            observation_dim, hidden_cells=cells, out_key="state_value", activation_class=nn.Tanh
        )
        self.cost_critic = make_value_network(
            observation_dim, hidden_cells=cells, out_key="cost_value", activation_class=nn.Tanh
        )
        self.norm = None
        if config.normalize_observations:  # one normaliser in front of all three networks
            self.norm = ObservationNormalizer.identity(observation_dim)
            self.actor = with_observation_norm(self.actor, self.norm)
            self.critic, self.cost_critic = (
                TensorDictModule(
                    nn.Sequential(self.norm, net.module), in_keys=net.in_keys, out_keys=net.out_keys
                )
                for net in (self.critic, self.cost_critic)
            )
            # running count, mean and sum of squared deviations of every observation seen (float64)
            self.register_buffer("obs_count", torch.zeros((), dtype=torch.float64))
            self.register_buffer("obs_mean", torch.zeros(observation_dim, dtype=torch.float64))
            self.register_buffer("obs_m2", torch.zeros(observation_dim, dtype=torch.float64))
        self.reward_gae = GAE(
            gamma=config.gamma, lmbda=config.gae_lambda, value_network=self.critic, average_gae=False
        )
        self.cost_gae = GAE(
            gamma=config.gamma, lmbda=config.gae_lambda, value_network=self.cost_critic, average_gae=False
        )
        self.cost_gae.set_keys(
            reward="cost", value="cost_value", advantage="cost_advantage", value_target="cost_value_target"
        )
        self.loss = ClipPPOLoss(
            self.actor,
            self.critic,
            clip_epsilon=config.clip_epsilon,
            entropy_coeff=config.entropy_coeff,
            loss_critic_type="l2",
            normalize_advantage=False,
        )
        self.optim = torch.optim.Adam(
            [
                {"params": self.loss.actor_network_params.values(True, True), "lr": config.actor_lr},
                {"params": self.loss.critic_network_params.values(True, True), "lr": config.critic_lr},
                {"params": self.cost_critic.parameters(), "lr": config.critic_lr},
            ]
        )
        # the multiplier: learned from lagrange_init (PPO-Lagrangian) or fixed at cost_penalty (0: plain PPO)
        multiplier = config.lagrange_init if config.lagrangian else config.cost_penalty
        self.lagrange = nn.Parameter(torch.tensor(float(multiplier)))
        self.lagrange_optim = torch.optim.Adam([self.lagrange], lr=config.lagrange_lr)

    def observe(self, observations: torch.Tensor) -> None:
        """Add a batch's observations to the running statistics and move the normaliser to them (Chan et al.'s
        parallel update of the mean and the sum of squared deviations)."""
        if self.norm is None:
            return
        x = observations.reshape(-1, observations.shape[-1]).double()
        n, mean = x.shape[0], x.mean(0)
        m2 = ((x - mean) ** 2).sum(0)
        total = self.obs_count + n
        delta = mean - self.obs_mean
        self.obs_mean += delta * n / total
        self.obs_m2 += m2 + delta**2 * self.obs_count * n / total
        self.obs_count.fill_(total)
        with torch.no_grad():
            self.norm.loc.copy_(self.obs_mean.float())
            self.norm.scale.copy_(((self.obs_m2 / total).sqrt() + STD_EPS).float())

    def training_state(self) -> dict:
        return {
            "networks": self.state_dict(),
            "optim": self.optim.state_dict(),
            "lagrange_optim": self.lagrange_optim.state_dict(),
        }

    def load_training_state(self, state: dict) -> None:
        self.load_state_dict(state["networks"])
        self.optim.load_state_dict(state["optim"])
        self.lagrange_optim.load_state_dict(state["lagrange_optim"])


def _check_finite(what: str, value: torch.Tensor, batch: int) -> None:
    advice = "lower the learning rates (ppo.actor_lr, ppo.critic_lr, ppo.lagrange_lr) or ppo.max_grad_norm"
    check_finite(what, value.detach(), f"batch {batch}", advice)


def _standardized(x: torch.Tensor) -> torch.Tensor:
    return (x - x.mean()) / (x.std() + 1e-8)


def ppo_update(
    learner: PPOLearner, batch: TensorDict, config: PPOConfig, index: int, cost: float, *, batches: int = 1
) -> int:
    """One batch's update: the multiplier's Adam step on the batch's mean episode cost ``cost`` (skipped
    without a finished episode; never with a fixed ``config.cost_penalty``), the advantages of the penalised
    objective, then ``epochs`` passes of clipped PPO over minibatches (actor, critic and cost critic each
    clipped to ``max_grad_norm``). With
    ``config.target_kl``, the passes stop after the first whose end finds the estimated KL divergence of the
    policy from the batch's own, the mean of ``log pi_old(a|s) - log pi(a|s)`` over the batch's actions, above
    it. With ``config.lr_decay``, the actor's learning rate is ``actor_lr * (1 - index / batches)``. Returns
    the number of passes made."""
    with torch.no_grad():
        learner.reward_gae(batch)
        learner.cost_gae(batch)
    if config.lagrangian and not math.isnan(cost):  # no finished episode: no new cost estimate, no step
        learner.lagrange_optim.zero_grad()
        (-learner.lagrange * (cost - config.cost_limit)).backward()
        learner.lagrange_optim.step()
        with torch.no_grad():
            learner.lagrange.clamp_(min=0.0)
    lagrange = float(learner.lagrange.detach())
    advantage, cost_advantage = batch["advantage"], batch["cost_advantage"]
    if config.advantage_standardization == "separate":  # OmniSafe: each standardised, then combined
        advantage, cost_advantage = _standardized(advantage), _standardized(cost_advantage)
    if config.lagrangian or config.cost_penalty:  # the penalised objective, lambda learned or fixed
        advantage = (advantage - lagrange * cost_advantage) / (1.0 + lagrange)
    batch["advantage"] = (
        _standardized(advantage) if config.advantage_standardization == "combined" else advantage
    )
    if config.lr_decay:
        learner.optim.param_groups[0]["lr"] = config.actor_lr * (1.0 - index / batches)
    buffer = TensorDictReplayBuffer(
        storage=LazyTensorStorage(batch.numel()),
        sampler=SamplerWithoutReplacement(),
        batch_size=config.minibatch_size,
    )
    flat = batch.reshape(-1)
    buffer.extend(flat)
    epochs = 0
    for _ in range(config.epochs):
        epochs += 1
        for _ in range(batch.numel() // config.minibatch_size):
            mb = buffer.sample()
            terms = learner.loss(mb)
            cost_pred = learner.cost_critic(mb.select("observation").clone())["cost_value"]
            cost_loss = (cost_pred - mb["cost_value_target"]).pow(2).mean()
            total = (
                terms["loss_objective"] + terms["loss_critic"] + terms.get("loss_entropy", 0.0) + cost_loss
            )
            _check_finite("the PPO loss", total, index)
            learner.optim.zero_grad()
            total.backward()
            for group in learner.optim.param_groups:  # actor, critic and cost critic clipped separately
                nn.utils.clip_grad_norm_(group["params"], config.max_grad_norm)
            learner.optim.step()
        if config.target_kl is not None and _kl_from_batch_policy(learner, flat) > config.target_kl:
            break
    for name, param in learner.named_parameters():
        _check_finite(f"parameter {name}", param, index)
    return epochs


def _kl_from_batch_policy(learner: PPOLearner, batch: TensorDict) -> float:
    """The sample estimate of KL(pi_old || pi) on the batch's actions, pi_old the policy that collected them."""
    with torch.no_grad():
        log_prob = learner.actor.get_dist(batch.select("observation").clone()).log_prob(batch["action"])
        return float((batch["action_log_prob"] - log_prob.reshape(batch["action_log_prob"].shape)).mean())
