"""Each algorithm of the DSRL recipe as (optional) pre-training plus one :class:`MultiLossStepper`.

An algorithm builder takes the algorithm's settings (a mapping, e.g. the Hydra ``algo`` group), the
:class:`~spoil_torchrl.data.DualDemoBuffers` and the observation / action sizes, does whatever must happen
before the policy is trained (SpoilDICE: stage 1 of Algorithm 1 -- the discriminators C_P and C_S, the support
cut, and the one-time annotation of the unlabeled storage), and returns :class:`PolicyTraining`: the losses
and optimisers of the main stage and the loss that owns the policy. ``ALGORITHMS`` maps the ``algo.name`` of
the recipe to its builder; adding a baseline means adding a builder here and a config in ``configs/algo/``
(a baseline that needs a role other than D_S, D_P, D_U lists it in the config's ``extra_roles``, as SafeDICE
does with its non-preferred D_N). Every builder also takes the :class:`EpisodeConstraint` of the run (the
dataset's episode-cost threshold and the task's horizon); only COptiDICE, which constrains the true cost,
reads it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import LossModule

from spoil_torchrl.data.buffers import DualDemoBuffers
from spoil_torchrl.data.labeling import episode_stats
from spoil_torchrl.modules import (
    ObservationNormalizer,
    make_actor,
    make_discriminator,
    make_value_network,
    with_observation_norm,
)
from spoil_torchrl.objectives import (
    COptiDICELoss,
    DemoDICELoss,
    DWBCLoss,
    PUDiscriminatorLoss,
    SafeDICELoss,
    SpoilDICELoss,
    SupportEstimator,
    WeightedBCLoss,
    per_step_cost_limit,
    safedice_auto_alpha,
    safedice_reward,
)
from spoil_torchrl.trainers.compiled import CompiledStepper
from spoil_torchrl.trainers.offline import MultiLossStepper, StepEvery, offline_trainer
from spoil_torchrl.trainers.settings import SettingsError


@dataclass(frozen=True)
class EpisodeConstraint:
    """The run's safety constraint as the evaluation sees it: episodes of at most ``episode_length`` steps (the
    task's time limit T) whose summed cost should stay within ``cost_threshold`` (the prepared dataset's)."""

    cost_threshold: float
    episode_length: int


@dataclass
class PolicyTraining:
    """What the recipe trains in its main stage.

    Attributes:
        stepper: the optimisation step (losses in order, their optimisers and schedules).
        policy_loss: the loss holding the policy (``actor_network`` / ``actor_network_params``).
        diagnostics: extra numbers measured before the main stage (e.g. the support share of D_U).
        dice: the DICE loss of the main stage, if any (it writes ``dice_weight`` / ``dice_advantage`` into
            ``dice_role``'s transitions; :func:`~spoil_torchrl.eval.dice_diagnostics.dice_diagnostics` reads it).
        dice_role: the role the DICE loss weights (D_U, or D_S for DemoDICE-S).
        observation_norm: the statistics the training data were standardised with, if any.
    """

    stepper: MultiLossStepper
    policy_loss: LossModule
    diagnostics: dict[str, float]
    dice: LossModule | None = None
    dice_role: str | None = None
    observation_norm: ObservationNormalizer | None = None

    @contextlib.contextmanager
    def policy(self) -> Iterator[ProbabilisticActor]:
        """The current policy as a plain module (the loss's functional parameters put in place). When the
        training data were standardised (``observation_norm``), the policy standardises raw observations
        itself, so it can act in the environment and be saved as one self-contained file."""
        loss = self.policy_loss
        with loss.actor_network_params.to_module(loss.actor_network):
            if self.observation_norm is None:
                yield loss.actor_network
            else:
                yield with_observation_norm(loss.actor_network, self.observation_norm)


def _actor(cfg: Mapping[str, Any], obs_dim: int, act_dim: int) -> ProbabilisticActor:
    return make_actor(
        obs_dim, act_dim, hidden_cells=tuple(cfg["hidden_cells"]), distribution=cfg["distribution"]
    )


def _adam(params, lr: float) -> torch.optim.Adam:
    return torch.optim.Adam(list(params), lr=float(lr))


def _weighted_bc(
    cfg: Mapping[str, Any], obs_dim: int, act_dim: int, role: str, weight: str | None, diagnostics: dict
) -> PolicyTraining:
    """A main stage of weighted BC alone (Eq. 20 on ``role`` with ``weight``): BC, FBC, JFBC."""
    policy_loss = WeightedBCLoss(_actor(cfg, obs_dim, act_dim), role=role, weight=weight)
    stepper = MultiLossStepper({"actor": policy_loss}, [_adam(policy_loss.parameters(), cfg["actor_lr"])])
    return PolicyTraining(stepper, policy_loss, diagnostics)


def _dice_with_extraction(
    cfg: Mapping[str, Any],
    dice: LossModule,
    dual_optimizers: list[torch.optim.Optimizer],
    obs_dim: int,
    act_dim: int,
    role: str,
    diagnostics: dict,
) -> PolicyTraining:
    """A DICE main stage: ``dice`` writes ``dice_weight`` into ``role`` and pi is weighted BC on it (Eq. 20);
    the dual's optimisers step first, then the actor's."""
    policy_loss = WeightedBCLoss(_actor(cfg, obs_dim, act_dim), role=role, weight="dice_weight")
    optimizers = [*dual_optimizers, _adam(policy_loss.parameters(), cfg["actor_lr"])]
    stepper = MultiLossStepper({"dice": dice, "actor": policy_loss}, optimizers)
    return PolicyTraining(stepper, policy_loss, diagnostics, dice=dice, dice_role=role)


def train_discriminators(
    cfg: Mapping[str, Any],
    buffers: DualDemoBuffers,
    obs_dim: int,
    act_dim: int,
    *,
    positives: tuple[str, ...] = ("performant", "safe"),
    against: str = "unlabeled",
    logger=None,
    progress: bool = True,
) -> dict[str, PUDiscriminatorLoss]:
    """Algorithm 1, "pretrain C_P and C_S": one :class:`PUDiscriminatorLoss` per positive role against
    ``against`` (default ``"unlabeled"``: Eq. 16-17; DemoDICE-S uses ``"safe"``), trained for ``cfg["steps"]``
    steps with Adam (``cfg["lr"]``) through the offline :class:`~torchrl.trainers.Trainer`.
    ``cfg["gradient_penalty"]`` maps each positive role to its penalty coefficient (Table J: 10 for C_P, none
    for C_S). ``cfg["compile"]`` (default false) steps them with a :class:`CompiledStepper`."""
    penalties = cfg["gradient_penalty"]
    missing = [role for role in positives if role not in penalties]
    if missing:
        raise ValueError(f"discriminator.gradient_penalty has no coefficient for {missing}")
    losses = {
        f"disc_{role}": PUDiscriminatorLoss(
            make_discriminator(obs_dim, act_dim, hidden_cells=tuple(cfg["hidden_cells"])),
            positive=role,
            unlabeled=against,
            gradient_penalty=float(penalties[role]),
        )
        for role in positives
    }
    optimizers = [_adam(loss.parameters(), cfg["lr"]) for loss in losses.values()]
    stepper_class = CompiledStepper if cfg.get("compile", False) else MultiLossStepper
    trainer = offline_trainer(
        stepper_class(losses, optimizers),
        buffers.sample,
        total_steps=int(cfg["steps"]),
        steps_per_batch=min(100, int(cfg["steps"])),
        logger=logger,
        progress_bar=progress,
        progress_label=f"pre-training {', '.join(f'C_{role[0].upper()}' for role in positives)}",
    )
    trainer.train()
    return {name.removeprefix("disc_"): loss for name, loss in losses.items()}


def build_spoildice(
    cfg: Mapping[str, Any],
    buffers: DualDemoBuffers,
    obs_dim: int,
    act_dim: int,
    *,
    logger=None,
    progress: bool = True,
    constraint: EpisodeConstraint | None = None,
) -> PolicyTraining:
    """SpoilDICE (Algorithm 1). Stage 1: C_P and C_S (Eq. 16-17), log r_P (Eq. 18), the kappa-quantile support
    cut fitted on D_S (Eq. 13), and D_U annotated once with ``log_ratio_performant`` and ``safe_support``.
    Main stage: (nu, lambda) by Eq. (19) and pi by weighted BC on D_U (Eq. 20)."""
    discriminators = train_discriminators(
        cfg["discriminator"], buffers, obs_dim, act_dim, logger=logger, progress=progress
    )
    ratio_p = discriminators["performant"].log_ratio_module("log_ratio_performant")
    support = _fit_support(discriminators["safe"], buffers, "safe", float(cfg["kappa"]), "safe_support")
    buffers.annotate("unlabeled", ratio_p)
    buffers.annotate("unlabeled", support)
    buffers.annotate("performant", support)  # read by the diagnostics only (the share of D_P kept)
    unlabeled = buffers["unlabeled"].storage[:]
    diagnostics = {
        "support_share_unlabeled": float(unlabeled["safe_support"].float().mean()),
        "support_threshold": float(support.threshold),
        "log_ratio_performant_mean": float(unlabeled["log_ratio_performant"].float().mean()),
    }
    dice = SpoilDICELoss(
        make_value_network(obs_dim, hidden_cells=tuple(cfg["hidden_cells"])),
        gamma=float(cfg["gamma"]),
        gradient_penalty=float(cfg["nu_gradient_penalty"]),
        init_lagrange=float(cfg["init_lagrange"]),
    )
    dual = [
        _adam(dice.nu_network_params.values(True, True), cfg["nu_lr"]),
        _adam([dice.lagrange], cfg["lagrange_lr"]),
    ]
    return _dice_with_extraction(cfg, dice, dual, obs_dim, act_dim, "unlabeled", diagnostics)


def build_bc(
    cfg: Mapping[str, Any],
    buffers: DualDemoBuffers,
    obs_dim: int,
    act_dim: int,
    *,
    logger=None,
    progress: bool = True,
    constraint: EpisodeConstraint | None = None,
) -> PolicyTraining:
    """BC: maximum likelihood on D_P (``cfg["role"]``, default ``"performant"``), no pre-training."""
    return _weighted_bc(cfg, obs_dim, act_dim, cfg.get("role", "performant"), None, {})


def _fit_support(
    loss: PUDiscriminatorLoss, buffers: DualDemoBuffers, role: str, kappa: float, out_key: str
) -> SupportEstimator:
    """Eq. (13) on ``role``'s discriminator: the kappa-quantile cut of its log-ratio over ``role``'s data."""
    return SupportEstimator(loss.frozen_network(), kappa=kappa, out_key=out_key).fit(buffers[role].storage[:])


def build_fbc(
    cfg: Mapping[str, Any],
    buffers: DualDemoBuffers,
    obs_dim: int,
    act_dim: int,
    *,
    logger=None,
    progress: bool = True,
    constraint: EpisodeConstraint | None = None,
) -> PolicyTraining:
    """Filtered BC (paper section 5, Table B): NLL on D_P weighted by the estimated safe support 1_S (C_S
    against D_U, the kappa cut on D_S), i.e. BC on the performant transitions inside the safe support.

    ``cfg["support"] = "oracle"`` (``+algo.support=oracle``; default ``"estimated"``) is an ablation that no
    method can run on real data: the weight is 1 on D_P's
    trajectories whose true episode cost is within the limit (``constraint``) and 0 elsewhere, i.e. BC on D_P's
    safe trajectories, the filter FBC's estimate approximates. It measures what the estimate's errors cost."""
    support = cfg.get("support", "estimated")
    if support not in ("estimated", "oracle"):
        raise SettingsError(f"algo.support = {support!r}: expected estimated or oracle")
    if support == "oracle":
        if constraint is None:
            raise ValueError(
                "FBC with support=oracle needs the cost limit: pass constraint=EpisodeConstraint(...)"
            )
        cost = episode_stats(buffers["performant"].storage[:])["cost"]
        limit = constraint.cost_threshold
        buffers.annotate(
            "performant",
            "safe_support",
            lambda td: (
                (cost[td["episode"]] <= limit)
                .to(td["next", "reward"].dtype)
                .reshape(td["next", "reward"].shape)
            ),
        )
    else:
        discriminators = train_discriminators(
            cfg["discriminator"],
            buffers,
            obs_dim,
            act_dim,
            positives=("safe",),
            logger=logger,
            progress=progress,
        )
        support = _fit_support(discriminators["safe"], buffers, "safe", float(cfg["kappa"]), "safe_support")
        buffers.annotate("performant", support)
    share = float(buffers["performant"].storage[:]["safe_support"].float().mean())
    return _weighted_bc(
        cfg, obs_dim, act_dim, "performant", "safe_support", {"support_share_performant": share}
    )


def build_jfbc(
    cfg: Mapping[str, Any],
    buffers: DualDemoBuffers,
    obs_dim: int,
    act_dim: int,
    *,
    logger=None,
    progress: bool = True,
    constraint: EpisodeConstraint | None = None,
) -> PolicyTraining:
    """Joint filtered BC (paper section 5): NLL on D_U weighted by 1_S * 1_P, both kappa cuts (Eq. 13) of
    discriminators trained against D_U (C_S on D_S, C_P on D_P)."""
    discriminators = train_discriminators(
        cfg["discriminator"], buffers, obs_dim, act_dim, logger=logger, progress=progress
    )
    kappa = float(cfg["kappa"])
    buffers.annotate(
        "unlabeled", _fit_support(discriminators["safe"], buffers, "safe", kappa, "safe_support")
    )
    buffers.annotate(
        "unlabeled",
        _fit_support(discriminators["performant"], buffers, "performant", kappa, "performant_support"),
    )
    buffers.annotate("unlabeled", "jfbc_weight", lambda td: td["safe_support"] * td["performant_support"])
    unlabeled = buffers["unlabeled"].storage[:]
    diagnostics = {
        "support_share_unlabeled": float(unlabeled["safe_support"].float().mean()),
        "performant_share_unlabeled": float(unlabeled["performant_support"].float().mean()),
        "jfbc_share_unlabeled": float(unlabeled["jfbc_weight"].float().mean()),
    }
    return _weighted_bc(cfg, obs_dim, act_dim, "unlabeled", "jfbc_weight", diagnostics)


def _demodice_stage(
    cfg: Mapping[str, Any],
    buffers: DualDemoBuffers,
    obs_dim: int,
    act_dim: int,
    *,
    role: str,
    reward_key: str,
    diagnostics: dict,
) -> PolicyTraining:
    """DemoDICE's main stage on ``role``'s samples with the annotated reward ``reward_key``: nu by DemoDICE's
    dual and pi by weighted BC on the role (see :class:`DemoDICELoss`)."""
    reward = buffers[role].storage[:][reward_key].float()
    diagnostics = diagnostics | {
        f"{reward_key}_mean": float(reward.mean()),
        f"{reward_key}_std": float(reward.std()),
    }
    dice = DemoDICELoss(
        make_value_network(obs_dim, hidden_cells=tuple(cfg["hidden_cells"])),
        alpha=float(cfg["alpha"]),
        gamma=float(cfg["gamma"]),
        gradient_penalty=float(cfg["nu_gradient_penalty"]),
        regularization=role,
        reward=reward_key,
    )
    dual = [_adam(dice.nu_network_params.values(True, True), cfg["nu_lr"])]
    return _dice_with_extraction(cfg, dice, dual, obs_dim, act_dim, role, diagnostics)


def build_demodice_s(
    cfg: Mapping[str, Any],
    buffers: DualDemoBuffers,
    obs_dim: int,
    act_dim: int,
    *,
    logger=None,
    progress: bool = True,
    constraint: EpisodeConstraint | None = None,
) -> PolicyTraining:
    """DemoDICE-S (paper section 5): min KL(d||d_P) + alpha KL(d||d_S) with D_S as the samples. C_P is trained
    against D_S, so its logit is the reward log d_P/d_S; D_S is annotated with ``log_ratio_performant_safe``
    and the policy is weighted BC on D_S."""
    discriminators = train_discriminators(
        cfg["discriminator"],
        buffers,
        obs_dim,
        act_dim,
        positives=("performant",),
        against="safe",
        logger=logger,
        progress=progress,
    )
    buffers.annotate("safe", discriminators["performant"].log_ratio_module("log_ratio_performant_safe"))
    return _demodice_stage(
        cfg, buffers, obs_dim, act_dim, role="safe", reward_key="log_ratio_performant_safe", diagnostics={}
    )


def build_demodice_u(
    cfg: Mapping[str, Any],
    buffers: DualDemoBuffers,
    obs_dim: int,
    act_dim: int,
    *,
    logger=None,
    progress: bool = True,
    constraint: EpisodeConstraint | None = None,
) -> PolicyTraining:
    """DemoDICE-U (paper section 5: "variants of DemoDICE that regularize d toward d_S, differing in the choice
    of importance sampling distribution"): DemoDICE-S's objective min KL(d||d_P) + alpha KL(d||d_S), with D_U
    as the samples. With w = d/d_U it is DemoDICE's dual on D_U with the reward log r_P + alpha log r_S
    (``demodice_reward``), from C_P and C_S trained against D_U (Eq. 16-18); the policy is weighted BC on D_U."""
    discriminators = train_discriminators(
        cfg["discriminator"], buffers, obs_dim, act_dim, logger=logger, progress=progress
    )
    buffers.annotate("unlabeled", discriminators["performant"].log_ratio_module("log_ratio_performant"))
    buffers.annotate("unlabeled", discriminators["safe"].log_ratio_module("log_ratio_safe"))
    alpha = float(cfg["alpha"])
    buffers.annotate(
        "unlabeled",
        "demodice_reward",
        lambda td: td["log_ratio_performant"] + alpha * td["log_ratio_safe"],
    )
    log_ratio_safe = buffers["unlabeled"].storage[:]["log_ratio_safe"].float()
    diagnostics = {
        "log_ratio_safe_mean": float(log_ratio_safe.mean()),
        "log_ratio_safe_std": float(log_ratio_safe.std()),
    }
    return _demodice_stage(
        cfg,
        buffers,
        obs_dim,
        act_dim,
        role="unlabeled",
        reward_key="demodice_reward",
        diagnostics=diagnostics,
    )


def build_safedice(
    cfg: Mapping[str, Any],
    buffers: DualDemoBuffers,
    obs_dim: int,
    act_dim: int,
    *,
    logger=None,
    progress: bool = True,
    constraint: EpisodeConstraint | None = None,
) -> PolicyTraining:
    """SafeDICE (Jang et al., 2023; paper section 5 with the unsafe episodes as non-preferred D_N). Stage 1: the
    discriminator of D_N against D_U (Eq. 16 with D_N as positives), frozen; D_U annotated once with its logit
    ``log_ratio_nonpreferred``; alpha = ``cfg["alpha"]``, or :func:`safedice_auto_alpha` of D over all of D_U for
    ``"auto"``; with ``cfg["standardize_reward"]`` the reward is standardised by its mean and standard deviation
    over D_U, as the reference code does. Main stage: nu by SafeDICE's dual and pi by weighted BC on D_U."""
    if "nonpreferred" not in buffers.roles:
        raise ValueError(
            "SafeDICE needs a 'nonpreferred' role (D_N) in the buffers: list it in algo.extra_roles "
            "(configs/algo/safedice.yaml does) so that prepare_dataset selects it"
        )
    discriminators = train_discriminators(
        cfg["discriminator"],
        buffers,
        obs_dim,
        act_dim,
        positives=("nonpreferred",),
        logger=logger,
        progress=progress,
    )
    buffers.annotate("unlabeled", discriminators["nonpreferred"].log_ratio_module("log_ratio_nonpreferred"))
    probability = torch.sigmoid(
        buffers["unlabeled"].storage[:]["log_ratio_nonpreferred"].double().reshape(-1)
    )
    alpha = safedice_auto_alpha(probability) if str(cfg["alpha"]) == "auto" else float(cfg["alpha"])
    reward = safedice_reward(probability, alpha)
    mean, std = float(reward.mean()), float(reward.std(unbiased=False))  # NumPy's std, as the reference
    reward_mean, reward_std = 0.0, 1.0
    if bool(cfg.get("standardize_reward", False)):
        reward_mean, reward_std = mean, (std if std > 0 else 1.0)
    diagnostics = {
        "alpha": alpha,
        "reward_mean": mean,
        "reward_std": std,
        "nonpreferred_probability_mean": float(probability.mean()),
    }
    dice = SafeDICELoss(
        make_value_network(obs_dim, hidden_cells=tuple(cfg["hidden_cells"])),
        alpha=alpha,
        gamma=float(cfg["gamma"]),
        gradient_penalty=float(cfg["nu_gradient_penalty"]),
        reward_mean=reward_mean,
        reward_std=reward_std,
    )
    dual = [_adam(dice.nu_network_params.values(True, True), cfg["nu_lr"])]
    return _dice_with_extraction(cfg, dice, dual, obs_dim, act_dim, "unlabeled", diagnostics)


def build_dwbc_s(
    cfg: Mapping[str, Any],
    buffers: DualDemoBuffers,
    obs_dim: int,
    act_dim: int,
    *,
    logger=None,
    progress: bool = True,
    constraint: EpisodeConstraint | None = None,
) -> PolicyTraining:
    """DWBC-S (paper section 5; Xu et al., 2022): DWBC with ``cfg["expert"]`` (D_P) as its expert data and
    ``cfg["unlabeled"]`` (D_S) as its unlabeled data, "recovering performant behaviours from safe demonstrations"
    (see :class:`DWBCLoss`). No pre-training: the discriminator D(s, a, log pi) and the policy are trained jointly
    by one loss; the discriminator's optimiser steps every ``cfg["discriminator"]["update_interval"]`` steps (the
    reference code: 100)."""
    roles = (cfg["expert"], cfg["unlabeled"])
    missing = [role for role in roles if role not in buffers.roles]
    if missing:
        raise ValueError(f"DWBC-S reads the roles {roles}, but the buffers have no {missing}")
    disc = cfg["discriminator"]
    loss = DWBCLoss(
        _actor(cfg, obs_dim, act_dim),
        make_discriminator(
            obs_dim, act_dim, hidden_cells=tuple(disc["hidden_cells"]), extra_inputs={"policy_log_prob": 1}
        ),
        alpha=float(cfg["alpha"]),
        eta=float(cfg["eta"]),
        reference_offsets=bool(cfg.get("reference_offsets", True)),
        expert=cfg["expert"],
        unlabeled=cfg["unlabeled"],
    )
    optimizers = [
        _adam(loss.actor_network_params.values(True, True), cfg["actor_lr"]),
        StepEvery(
            _adam(loss.discriminator_network_params.values(True, True), disc["lr"]),
            int(disc["update_interval"]),
        ),
    ]
    return PolicyTraining(MultiLossStepper({"dwbc": loss}, optimizers), loss, {})


def build_coptidice(
    cfg: Mapping[str, Any],
    buffers: DualDemoBuffers,
    obs_dim: int,
    act_dim: int,
    *,
    logger=None,
    progress: bool = True,
    constraint: EpisodeConstraint | None = None,
) -> PolicyTraining:
    """COptiDICE (Lee et al., 2022; paper section 5 with the dataset's true reward and cost on D_U). No
    pre-training; main stage: (nu, chi, tau, lambda) by :class:`COptiDICELoss` and pi by weighted BC on D_U. The
    per-step cost limit is ``cfg["cost_limit"]`` when set, else :func:`per_step_cost_limit` of the
    ``constraint``'s episode threshold over its episode length (the main recipe passes the dataset's threshold
    and the task's time limit)."""
    gamma = float(cfg["gamma"])
    limit = cfg.get("cost_limit")
    if limit is None:
        if constraint is None:
            raise ValueError(
                "COptiDICE needs its cost limit: pass constraint=EpisodeConstraint(threshold, episode_length) "
                "or set algo.cost_limit (per step, on the normalised discounted occupancy)"
            )
        limit = per_step_cost_limit(constraint.cost_threshold, constraint.episode_length, gamma)
    unlabeled = buffers["unlabeled"].storage[:]
    diagnostics = {
        "cost_limit": float(limit),
        "cost_rate_unlabeled": float(unlabeled["next", "cost"].float().mean()),
        "reward_rate_unlabeled": float(unlabeled["next", "reward"].float().mean()),
    }
    hidden = tuple(cfg["hidden_cells"])
    dice = COptiDICELoss(
        make_value_network(obs_dim, hidden_cells=hidden),
        make_value_network(obs_dim, hidden_cells=hidden, out_key="chi"),
        cost_limit=float(limit),
        alpha=float(cfg["alpha"]),
        gamma=gamma,
        cost_ub_epsilon=float(cfg["cost_ub_epsilon"]),
        gradient_penalty=float(cfg["nu_gradient_penalty"]),
        init_lagrange=float(cfg["init_lagrange"]),
    )
    dual = [
        _adam(dice.nu_network_params.values(True, True), cfg["nu_lr"]),
        _adam(dice.chi_network_params.values(True, True), cfg["nu_lr"]),
        _adam([dice.lagrange_param, dice.tau_param], cfg["lagrange_lr"]),
    ]
    return _dice_with_extraction(cfg, dice, dual, obs_dim, act_dim, "unlabeled", diagnostics)


ALGORITHMS: dict[str, Callable[..., PolicyTraining]] = {
    "spoildice": build_spoildice,
    "bc": build_bc,
    "fbc": build_fbc,
    "jfbc": build_jfbc,
    "demodice_s": build_demodice_s,
    "demodice_u": build_demodice_u,
    "safedice": build_safedice,
    "dwbc_s": build_dwbc_s,
    "coptidice": build_coptidice,
}
