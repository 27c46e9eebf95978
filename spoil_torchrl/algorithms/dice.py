"""The DICE algorithms: SpoilDICE (Algorithm 1) and the DICE baselines of the paper's section 5 (DemoDICE-S,
DemoDICE-U, SafeDICE, COptiDICE), each an :class:`~spoil_torchrl.algorithms.base.Algorithm`: a pre-training
``pretrain_<name>(cfg, context) -> Pretraining`` (none for COptiDICE) and a main stage
``build_<name>(cfg, context, pretraining) -> PolicyTraining``, a dual
(:class:`~spoil_torchrl.objectives.dice.DICELoss`) followed by weighted BC on its weights."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from spoil_torchrl.algorithms.base import (
    BuildContext,
    PolicyTraining,
    Pretraining,
    adam,
    dice_stage,
)
from spoil_torchrl.algorithms.constraints import constraint_roles_of, fit_constraint_supports
from spoil_torchrl.algorithms.discriminators import fit_support, frozen_networks, train_discriminators
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


def pretrain_spoildice(cfg: Mapping[str, Any], context: BuildContext) -> Pretraining:
    """SpoilDICE's stage 1 (Algorithm 1): C_P and C_S (Eq. 16-17), log r_P (Eq. 18), the kappa-quantile support
    cut fitted on D_S (Eq. 13), and D_U annotated once with ``log_ratio_performant`` and ``safe_support`` (D_P
    with ``safe_support`` too, read by the diagnostics only: the share of D_P kept).

    With several constraints (roles ``safe_<name>`` in the buffers) it is :func:`pretrain_spoildice_constraints`."""
    buffers = context.buffers
    if constraint_roles_of(buffers):
        return pretrain_spoildice_constraints(cfg, context)
    discriminators = train_discriminators(cfg["discriminator"], context)
    ratio_p = discriminators["performant"].log_ratio_module("log_ratio_performant")
    support = fit_support(discriminators["safe"], buffers, "safe", float(cfg["kappa"]), "safe_support")
    buffers.annotate("unlabeled", ratio_p)
    buffers.annotate("unlabeled", support)
    buffers.annotate("performant", support)
    unlabeled = buffers["unlabeled"].storage[:]
    diagnostics = {
        "support_share_unlabeled": float(unlabeled["safe_support"].float().mean()),
        "support_threshold": float(support.threshold),
        "log_ratio_performant_mean": float(unlabeled["log_ratio_performant"].float().mean()),
    }
    keys = {"unlabeled": ["log_ratio_performant", "safe_support"], "performant": ["safe_support"]}
    return Pretraining.of(buffers, keys, diagnostics, frozen_networks(discriminators))


def pretrain_spoildice_constraints(cfg: Mapping[str, Any], context: BuildContext) -> Pretraining:
    """SpoilDICE's stage 1 with K constraints (``docs/several_constraints.md``): C_P, and one C_S^k per
    constraint trained on its safe set ``safe_<name>`` against D_U (with C_S's gradient penalty), one kappa cut
    per constraint (Eq. 13 on D_S^k), and D_U annotated once with ``log_ratio_performant`` and ``safe_support``
    holding the K indicators ``[n, K]`` (each also as ``safe_support_<name>``). D_P gets the indicator of the
    intersection as ``safe_support`` (diagnostics: the share of D_P inside every support). Refuses supports with
    no transition of D_U in common (:func:`~spoil_torchrl.algorithms.constraints.fit_constraint_supports`)."""
    buffers = context.buffers
    discriminators, columns, diagnostics = fit_constraint_supports(
        cfg, context, stacked=("unlabeled",), intersected=("performant",), positives=("performant",)
    )
    buffers.annotate("unlabeled", discriminators["performant"].log_ratio_module("log_ratio_performant"))
    unlabeled = buffers["unlabeled"].storage[:]
    diagnostics["log_ratio_performant_mean"] = float(unlabeled["log_ratio_performant"].float().mean())
    keys = {
        "unlabeled": ["log_ratio_performant", "safe_support", *columns],
        "performant": ["safe_support", *columns],
    }
    return Pretraining.of(buffers, keys, diagnostics, frozen_networks(discriminators))


def build_spoildice(
    cfg: Mapping[str, Any], context: BuildContext, pretraining: Pretraining
) -> PolicyTraining:
    """SpoilDICE's main stage (Algorithm 1): (nu, lambda) by Eq. (19) and pi by weighted BC on D_U (Eq. 20),
    on D_U annotated by :func:`pretrain_spoildice` (with K constraints, one lambda_k each)."""
    constraints = len(constraint_roles_of(context.buffers))
    dice = context.place(
        SpoilDICELoss(
            _value_network(cfg, context),
            gamma=float(cfg["gamma"]),
            gradient_penalty=float(cfg["nu_gradient_penalty"]),
            init_lagrange=float(cfg["init_lagrange"]),
            **({"constraints": constraints} if constraints else {}),
        )
    )
    dual = [
        adam(dice.nu_network_params.values(True, True), cfg["nu_lr"]),
        adam([dice.lagrange], cfg["lagrange_lr"]),
    ]
    return dice_stage(cfg, context, dice, dual, "unlabeled", dict(pretraining.diagnostics))


def _demodice_stage(
    cfg: Mapping[str, Any], context: BuildContext, *, role: str, reward_key: str, diagnostics: Mapping
) -> PolicyTraining:
    """DemoDICE's main stage on ``role``'s samples with the annotated reward ``reward_key``: nu by DemoDICE's
    dual and pi by weighted BC on the role (see :class:`DemoDICELoss`)."""
    reward = context.buffers[role].storage[:][reward_key].float()
    diagnostics = dict(diagnostics) | {
        f"{reward_key}_mean": float(reward.mean()),
        f"{reward_key}_std": float(reward.std()),
    }
    dice = context.place(
        DemoDICELoss(
            _value_network(cfg, context),
            alpha=float(cfg["alpha"]),
            gamma=float(cfg["gamma"]),
            gradient_penalty=float(cfg["nu_gradient_penalty"]),
            regularization=role,
            reward=reward_key,
        )
    )
    dual = [adam(dice.nu_network_params.values(True, True), cfg["nu_lr"])]
    return dice_stage(cfg, context, dice, dual, role, diagnostics)


def pretrain_demodice_s(cfg: Mapping[str, Any], context: BuildContext) -> Pretraining:
    """DemoDICE-S's pre-training (paper section 5): C_P trained against D_S, so its logit is the reward
    log d_P/d_S; D_S annotated with it as ``log_ratio_performant_safe``."""
    discriminators = train_discriminators(
        cfg["discriminator"], context, positives=("performant",), against="safe"
    )
    context.buffers.annotate(
        "safe", discriminators["performant"].log_ratio_module("log_ratio_performant_safe")
    )
    keys = {"safe": ["log_ratio_performant_safe"]}
    return Pretraining.of(context.buffers, keys, {}, frozen_networks(discriminators))


def build_demodice_s(
    cfg: Mapping[str, Any], context: BuildContext, pretraining: Pretraining
) -> PolicyTraining:
    """DemoDICE-S's main stage: min KL(d||d_P) + alpha KL(d||d_S) with D_S as the samples, the reward from
    :func:`pretrain_demodice_s`, and the policy weighted BC on D_S."""
    return _demodice_stage(
        cfg, context, role="safe", reward_key="log_ratio_performant_safe", diagnostics=pretraining.diagnostics
    )


def pretrain_demodice_u(cfg: Mapping[str, Any], context: BuildContext) -> Pretraining:
    """DemoDICE-U's pre-training: C_P and C_S trained against D_U (Eq. 16-18), D_U annotated with their
    log-ratios and the reward log r_P + alpha log r_S (``demodice_reward``)."""
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
    keys = {"unlabeled": ["log_ratio_performant", "log_ratio_safe", "demodice_reward"]}
    return Pretraining.of(buffers, keys, diagnostics, frozen_networks(discriminators))


def build_demodice_u(
    cfg: Mapping[str, Any], context: BuildContext, pretraining: Pretraining
) -> PolicyTraining:
    """DemoDICE-U (paper section 5: "variants of DemoDICE that regularize d toward d_S, differing in the choice
    of importance sampling distribution"): DemoDICE-S's objective min KL(d||d_P) + alpha KL(d||d_S), with D_U
    as the samples. With w = d/d_U it is DemoDICE's dual on D_U with the reward of :func:`pretrain_demodice_u`;
    the policy is weighted BC on D_U."""
    return _demodice_stage(
        cfg, context, role="unlabeled", reward_key="demodice_reward", diagnostics=pretraining.diagnostics
    )


def pretrain_safedice(cfg: Mapping[str, Any], context: BuildContext) -> Pretraining:
    """SafeDICE's stage 1 (Jang et al., 2023; paper section 5 with the unsafe episodes as non-preferred D_N):
    the discriminator of D_N against D_U (Eq. 16 with D_N as positives), frozen; D_U annotated once with its
    logit ``log_ratio_nonpreferred``; alpha = ``cfg["alpha"]``, or :func:`safedice_auto_alpha` of D over all of
    D_U for ``"auto"``; the reward's mean and standard deviation over D_U."""
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
    diagnostics = {
        "alpha": alpha,
        "reward_mean": float(reward.mean()),
        "reward_std": float(reward.std(unbiased=False)),  # NumPy's std, as the reference
        "nonpreferred_probability_mean": float(probability.mean()),
    }
    keys = {"unlabeled": ["log_ratio_nonpreferred"]}
    return Pretraining.of(buffers, keys, diagnostics, frozen_networks(discriminators))


def build_safedice(cfg: Mapping[str, Any], context: BuildContext, pretraining: Pretraining) -> PolicyTraining:
    """SafeDICE's main stage: nu by SafeDICE's dual with the alpha of :func:`pretrain_safedice` and pi by
    weighted BC on D_U; with ``cfg["standardize_reward"]`` the reward is standardised by its mean and standard
    deviation over D_U, as the reference code does."""
    diagnostics = dict(pretraining.diagnostics)
    reward_mean, reward_std = 0.0, 1.0
    if bool(cfg.get("standardize_reward", False)):
        std = diagnostics["reward_std"]
        reward_mean, reward_std = diagnostics["reward_mean"], (std if std > 0 else 1.0)
    dice = context.place(
        SafeDICELoss(
            _value_network(cfg, context),
            alpha=diagnostics["alpha"],
            gamma=float(cfg["gamma"]),
            gradient_penalty=float(cfg["nu_gradient_penalty"]),
            reward_mean=reward_mean,
            reward_std=reward_std,
        )
    )
    dual = [adam(dice.nu_network_params.values(True, True), cfg["nu_lr"])]
    return dice_stage(cfg, context, dice, dual, "unlabeled", diagnostics)


def build_coptidice(
    cfg: Mapping[str, Any], context: BuildContext, pretraining: Pretraining
) -> PolicyTraining:
    """COptiDICE (Lee et al., 2022; paper section 5 with the dataset's true reward and cost on D_U). No
    pre-training (``pretraining`` is :data:`~spoil_torchrl.algorithms.base.NO_PRETRAINING`); main stage: (nu,
    chi, tau, lambda) by :class:`COptiDICELoss` and pi by weighted BC on D_U. The per-step cost limit is
    ``cfg["cost_limit"]`` when set, else :func:`per_step_cost_limit` of the context's
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
    dice = context.place(
        COptiDICELoss(
            _value_network(cfg, context),
            _value_network(cfg, context, out_key="chi"),
            cost_limit=float(limit),
            alpha=float(cfg["alpha"]),
            gamma=gamma,
            cost_ub_epsilon=float(cfg["cost_ub_epsilon"]),
            gradient_penalty=float(cfg["nu_gradient_penalty"]),
            init_lagrange=float(cfg["init_lagrange"]),
        )
    )
    dual = [
        adam(dice.nu_network_params.values(True, True), cfg["nu_lr"]),
        adam(dice.chi_network_params.values(True, True), cfg["nu_lr"]),
        adam([dice.lagrange_param, dice.tau_param], cfg["lagrange_lr"]),
    ]
    return dice_stage(cfg, context, dice, dual, "unlabeled", diagnostics)
