"""The behaviour-cloning baselines (paper section 5): BC, FBC, JFBC and DWBC-S, each an
:class:`~spoil_torchrl.algorithms.base.Algorithm`: a pre-training ``pretrain_<name>(cfg, context) -> Pretraining``
(FBC's and JFBC's support cuts; none for BC and DWBC-S) and a main stage
``build_<name>(cfg, context, pretraining) -> PolicyTraining``."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from spoil_torchrl.algorithms.base import (
    BuildContext,
    PolicyTraining,
    Pretraining,
    actor,
    adam,
    weighted_bc_stage,
)
from spoil_torchrl.algorithms.constraints import constraint_roles_of, fit_constraint_supports
from spoil_torchrl.algorithms.discriminators import fit_support, frozen_networks, train_discriminators
from spoil_torchrl.data.labeling import episode_stats
from spoil_torchrl.errors import SettingsError
from spoil_torchrl.modules import make_discriminator
from spoil_torchrl.objectives import DWBCLoss
from spoil_torchrl.trainers.offline import MultiLossStepper, StepEvery


def build_bc(cfg: Mapping[str, Any], context: BuildContext, pretraining: Pretraining) -> PolicyTraining:
    """BC: maximum likelihood on D_P (``cfg["role"]``, default ``"performant"``), no pre-training."""
    return weighted_bc_stage(cfg, context, cfg.get("role", "performant"), None, {})


def pretrain_fbc(cfg: Mapping[str, Any], context: BuildContext) -> Pretraining:
    """Filtered BC's pre-training (paper section 5, Table B): the estimated safe support 1_S (C_S against D_U,
    the kappa cut on D_S) annotated on D_P as ``safe_support``.

    ``cfg["support"] = "oracle"`` (``+algo.support=oracle``; default ``"estimated"``) is an ablation that no
    method can run on real data: the weight is 1 on D_P's trajectories whose true episode cost is within the
    limit (``context.constraint``) and 0 elsewhere, i.e. BC on D_P's safe trajectories, the filter FBC's
    estimate approximates. It measures what the estimate's errors cost.

    With several constraints (roles ``safe_<name>``, ``docs/several_constraints.md``) the filter is the
    intersection of the K estimated supports, one C_S^k and kappa cut per safe set
    (:func:`~spoil_torchrl.algorithms.constraints.fit_constraint_supports`): BC on D_P's transitions inside every
    support."""
    buffers = context.buffers
    support = cfg.get("support", "estimated")
    if support not in ("estimated", "oracle"):
        raise SettingsError(f"algo.support = {support!r}: expected estimated or oracle")
    networks = {}
    if constraint_roles_of(buffers):
        if support == "oracle":
            raise SettingsError(
                "algo.support = oracle takes the task's one cost; it does not apply to dataset.constraints"
            )
        discriminators, columns, diagnostics = fit_constraint_supports(
            cfg, context, intersected=("performant",)
        )
        keys = {"performant": ["safe_support", *columns]}
        return Pretraining.of(buffers, keys, diagnostics, frozen_networks(discriminators))
    if support == "oracle":
        if context.constraint is None:
            raise ValueError(
                "FBC with support=oracle needs the cost limit: pass constraint=EpisodeConstraint(...)"
            )
        cost = episode_stats(buffers["performant"].storage[:])["cost"]
        limit = context.constraint.cost_threshold
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
        discriminators = train_discriminators(cfg["discriminator"], context, positives=("safe",))
        support = fit_support(discriminators["safe"], buffers, "safe", float(cfg["kappa"]), "safe_support")
        buffers.annotate("performant", support)
        networks = frozen_networks(discriminators)
    share = float(buffers["performant"].storage[:]["safe_support"].float().mean())
    diagnostics = {"support_share_performant": share}
    return Pretraining.of(buffers, {"performant": ["safe_support"]}, diagnostics, networks)


def build_fbc(cfg: Mapping[str, Any], context: BuildContext, pretraining: Pretraining) -> PolicyTraining:
    """Filtered BC's main stage: NLL on D_P weighted by the safe support of :func:`pretrain_fbc`, i.e. BC on the
    performant transitions inside the safe support."""
    return weighted_bc_stage(cfg, context, "performant", "safe_support", dict(pretraining.diagnostics))


def pretrain_jfbc(cfg: Mapping[str, Any], context: BuildContext) -> Pretraining:
    """Joint filtered BC's pre-training (paper section 5): both kappa cuts (Eq. 13) of discriminators trained
    against D_U (C_S on D_S, C_P on D_P), and D_U annotated with their product ``jfbc_weight`` = 1_S * 1_P."""
    buffers = context.buffers
    discriminators = train_discriminators(cfg["discriminator"], context)
    kappa = float(cfg["kappa"])
    buffers.annotate("unlabeled", fit_support(discriminators["safe"], buffers, "safe", kappa, "safe_support"))
    buffers.annotate(
        "unlabeled",
        fit_support(discriminators["performant"], buffers, "performant", kappa, "performant_support"),
    )
    buffers.annotate("unlabeled", "jfbc_weight", lambda td: td["safe_support"] * td["performant_support"])
    unlabeled = buffers["unlabeled"].storage[:]
    diagnostics = {
        "support_share_unlabeled": float(unlabeled["safe_support"].float().mean()),
        "performant_share_unlabeled": float(unlabeled["performant_support"].float().mean()),
        "jfbc_share_unlabeled": float(unlabeled["jfbc_weight"].float().mean()),
    }
    keys = {"unlabeled": ["safe_support", "performant_support", "jfbc_weight"]}
    return Pretraining.of(buffers, keys, diagnostics, frozen_networks(discriminators))


def build_jfbc(cfg: Mapping[str, Any], context: BuildContext, pretraining: Pretraining) -> PolicyTraining:
    """Joint filtered BC's main stage: NLL on D_U weighted by :func:`pretrain_jfbc`'s ``jfbc_weight``."""
    return weighted_bc_stage(cfg, context, "unlabeled", "jfbc_weight", dict(pretraining.diagnostics))


def build_dwbc_s(cfg: Mapping[str, Any], context: BuildContext, pretraining: Pretraining) -> PolicyTraining:
    """DWBC-S (paper section 5; Xu et al., 2022): DWBC with ``cfg["expert"]`` (D_P) as its expert data and
    ``cfg["unlabeled"]`` (D_S) as its unlabeled data, "recovering performant behaviours from safe demonstrations"
    (see :class:`DWBCLoss`). No pre-training: the discriminator D(s, a, log pi) and the policy are trained jointly
    by one loss; the discriminator's optimiser steps every ``cfg["discriminator"]["update_interval"]`` steps (the
    reference code: 100)."""
    roles = (cfg["expert"], cfg["unlabeled"])
    missing = [role for role in roles if role not in context.buffers.roles]
    if missing:
        raise ValueError(f"DWBC-S reads the roles {roles}, but the buffers have no {missing}")
    disc = cfg["discriminator"]
    loss = context.place(
        DWBCLoss(
            actor(cfg, context),
            make_discriminator(
                context.observation_dim,
                context.action_dim,
                hidden_cells=tuple(disc["hidden_cells"]),
                extra_inputs={"policy_log_prob": 1},
            ),
            alpha=float(cfg["alpha"]),
            eta=float(cfg["eta"]),
            reference_offsets=bool(cfg.get("reference_offsets", True)),
            expert=cfg["expert"],
            unlabeled=cfg["unlabeled"],
        )
    )
    optimizers = [
        adam(loss.actor_network_params.values(True, True), cfg["actor_lr"]),
        StepEvery(
            adam(loss.discriminator_network_params.values(True, True), disc["lr"]),
            int(disc["update_interval"]),
        ),
    ]
    return PolicyTraining(MultiLossStepper({"dwbc": loss}, optimizers), loss, {})
