"""The DICE algorithms: SpoilDICE (Algorithm 1) and the DICE baselines of the paper's section 5 (DemoDICE-S,
DemoDICE-U, SafeDICE, COptiDICE), each a builder ``build_<name>(cfg, context) -> PolicyTraining`` whose main
stage is a dual (:class:`~spoil_torchrl.objectives.dice.DICELoss`) followed by weighted BC on its weights."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from spoil_torchrl.algorithms.base import (
    BuildContext,
    PolicyTraining,
    adam,
    dice_stage,
    fit_support,
    train_discriminators,
)
from spoil_torchrl.modules import make_value_network
from spoil_torchrl.objectives import (
    COptiDICELoss,
    DemoDICELoss,
    SafeDICELoss,
    SpoilDICELoss,
    per_step_cost_limit,
    safedice_auto_alpha,
    safedice_reward,
)


def _value_network(cfg: Mapping[str, Any], context: BuildContext, **kwargs):
    return make_value_network(context.observation_dim, hidden_cells=tuple(cfg["hidden_cells"]), **kwargs)


def build_spoildice(cfg: Mapping[str, Any], context: BuildContext) -> PolicyTraining:
    """SpoilDICE (Algorithm 1). Stage 1: C_P and C_S (Eq. 16-17), log r_P (Eq. 18), the kappa-quantile support
    cut fitted on D_S (Eq. 13), and D_U annotated once with ``log_ratio_performant`` and ``safe_support``.
    Main stage: (nu, lambda) by Eq. (19) and pi by weighted BC on D_U (Eq. 20)."""
    buffers = context.buffers
    discriminators = train_discriminators(cfg["discriminator"], context)
    ratio_p = discriminators["performant"].log_ratio_module("log_ratio_performant")
    support = fit_support(discriminators["safe"], buffers, "safe", float(cfg["kappa"]), "safe_support")
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
        _value_network(cfg, context),
        gamma=float(cfg["gamma"]),
        gradient_penalty=float(cfg["nu_gradient_penalty"]),
        init_lagrange=float(cfg["init_lagrange"]),
    )
    dual = [
        adam(dice.nu_network_params.values(True, True), cfg["nu_lr"]),
        adam([dice.lagrange], cfg["lagrange_lr"]),
    ]
    return dice_stage(cfg, context, dice, dual, "unlabeled", diagnostics)


def _demodice_stage(
    cfg: Mapping[str, Any], context: BuildContext, *, role: str, reward_key: str, diagnostics: dict
) -> PolicyTraining:
    """DemoDICE's main stage on ``role``'s samples with the annotated reward ``reward_key``: nu by DemoDICE's
    dual and pi by weighted BC on the role (see :class:`DemoDICELoss`)."""
    reward = context.buffers[role].storage[:][reward_key].float()
    diagnostics = diagnostics | {
        f"{reward_key}_mean": float(reward.mean()),
        f"{reward_key}_std": float(reward.std()),
    }
    dice = DemoDICELoss(
        _value_network(cfg, context),
        alpha=float(cfg["alpha"]),
        gamma=float(cfg["gamma"]),
        gradient_penalty=float(cfg["nu_gradient_penalty"]),
        regularization=role,
        reward=reward_key,
    )
    dual = [adam(dice.nu_network_params.values(True, True), cfg["nu_lr"])]
    return dice_stage(cfg, context, dice, dual, role, diagnostics)


def build_demodice_s(cfg: Mapping[str, Any], context: BuildContext) -> PolicyTraining:
    """DemoDICE-S (paper section 5): min KL(d||d_P) + alpha KL(d||d_S) with D_S as the samples. C_P is trained
    against D_S, so its logit is the reward log d_P/d_S; D_S is annotated with ``log_ratio_performant_safe``
    and the policy is weighted BC on D_S."""
    discriminators = train_discriminators(
        cfg["discriminator"], context, positives=("performant",), against="safe"
    )
    context.buffers.annotate(
        "safe", discriminators["performant"].log_ratio_module("log_ratio_performant_safe")
    )
    return _demodice_stage(cfg, context, role="safe", reward_key="log_ratio_performant_safe", diagnostics={})


def build_demodice_u(cfg: Mapping[str, Any], context: BuildContext) -> PolicyTraining:
    """DemoDICE-U (paper section 5: "variants of DemoDICE that regularize d toward d_S, differing in the choice
    of importance sampling distribution"): DemoDICE-S's objective min KL(d||d_P) + alpha KL(d||d_S), with D_U
    as the samples. With w = d/d_U it is DemoDICE's dual on D_U with the reward log r_P + alpha log r_S
    (``demodice_reward``), from C_P and C_S trained against D_U (Eq. 16-18); the policy is weighted BC on D_U."""
    buffers = context.buffers
    discriminators = train_discriminators(cfg["discriminator"], context)
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
        cfg, context, role="unlabeled", reward_key="demodice_reward", diagnostics=diagnostics
    )


def build_safedice(cfg: Mapping[str, Any], context: BuildContext) -> PolicyTraining:
    """SafeDICE (Jang et al., 2023; paper section 5 with the unsafe episodes as non-preferred D_N). Stage 1: the
    discriminator of D_N against D_U (Eq. 16 with D_N as positives), frozen; D_U annotated once with its logit
    ``log_ratio_nonpreferred``; alpha = ``cfg["alpha"]``, or :func:`safedice_auto_alpha` of D over all of D_U for
    ``"auto"``; with ``cfg["standardize_reward"]`` the reward is standardised by its mean and standard deviation
    over D_U, as the reference code does. Main stage: nu by SafeDICE's dual and pi by weighted BC on D_U."""
    buffers = context.buffers
    if "nonpreferred" not in buffers.roles:
        raise ValueError(
            "SafeDICE needs a 'nonpreferred' role (D_N) in the buffers: list it in algo.extra_roles "
            "(configs/algo/safedice.yaml does) so that prepare_dataset selects it"
        )
    discriminators = train_discriminators(cfg["discriminator"], context, positives=("nonpreferred",))
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
        _value_network(cfg, context),
        alpha=alpha,
        gamma=float(cfg["gamma"]),
        gradient_penalty=float(cfg["nu_gradient_penalty"]),
        reward_mean=reward_mean,
        reward_std=reward_std,
    )
    dual = [adam(dice.nu_network_params.values(True, True), cfg["nu_lr"])]
    return dice_stage(cfg, context, dice, dual, "unlabeled", diagnostics)


def build_coptidice(cfg: Mapping[str, Any], context: BuildContext) -> PolicyTraining:
    """COptiDICE (Lee et al., 2022; paper section 5 with the dataset's true reward and cost on D_U). No
    pre-training; main stage: (nu, chi, tau, lambda) by :class:`COptiDICELoss` and pi by weighted BC on D_U. The
    per-step cost limit is ``cfg["cost_limit"]`` when set, else :func:`per_step_cost_limit` of the context's
    ``constraint`` (the episode threshold over the episode length; the main recipe passes the dataset's
    threshold and the task's time limit)."""
    gamma = float(cfg["gamma"])
    limit = cfg.get("cost_limit")
    if limit is None:
        constraint = context.constraint
        if constraint is None:
            raise ValueError(
                "COptiDICE needs its cost limit: pass constraint=EpisodeConstraint(threshold, episode_length) "
                "or set algo.cost_limit (per step, on the normalised discounted occupancy)"
            )
        limit = per_step_cost_limit(constraint.cost_threshold, constraint.episode_length, gamma)
    unlabeled = context.buffers["unlabeled"].storage[:]
    diagnostics = {
        "cost_limit": float(limit),
        "cost_rate_unlabeled": float(unlabeled["next", "cost"].float().mean()),
        "reward_rate_unlabeled": float(unlabeled["next", "reward"].float().mean()),
    }
    dice = COptiDICELoss(
        _value_network(cfg, context),
        _value_network(cfg, context, out_key="chi"),
        cost_limit=float(limit),
        alpha=float(cfg["alpha"]),
        gamma=gamma,
        cost_ub_epsilon=float(cfg["cost_ub_epsilon"]),
        gradient_penalty=float(cfg["nu_gradient_penalty"]),
        init_lagrange=float(cfg["init_lagrange"]),
    )
    dual = [
        adam(dice.nu_network_params.values(True, True), cfg["nu_lr"]),
        adam(dice.chi_network_params.values(True, True), cfg["nu_lr"]),
        adam([dice.lagrange_param, dice.tau_param], cfg["lagrange_lr"]),
    ]
    return dice_stage(cfg, context, dice, dual, "unlabeled", diagnostics)
