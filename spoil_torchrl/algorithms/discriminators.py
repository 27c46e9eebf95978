"""Stage 1 of Algorithm 1, as every algorithm that pre-trains uses it: the PU discriminators
(:func:`train_discriminators`, Eq. 16-17), the kappa-quantile support cut on one of them (:func:`fit_support`,
Eq. 13), and the frozen networks a :class:`~spoil_torchrl.algorithms.base.Pretraining` keeps of them
(:func:`frozen_networks`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from spoil_torchrl.algorithms.base import BuildContext, adam
from spoil_torchrl.data.buffers import DualDemoBuffers
from spoil_torchrl.modules import make_discriminator
from spoil_torchrl.objectives import PUDiscriminatorLoss, SupportEstimator
from spoil_torchrl.trainers.compiled import CompiledStepper
from spoil_torchrl.trainers.offline import MultiLossStepper, offline_trainer


def train_discriminators(
    cfg: Mapping[str, Any],
    context: BuildContext,
    *,
    positives: tuple[str, ...] = ("performant", "safe"),
    against: str = "unlabeled",
) -> dict[str, PUDiscriminatorLoss]:
    """Algorithm 1, "pretrain C_P and C_S": one :class:`PUDiscriminatorLoss` per positive role against
    ``against`` (default ``"unlabeled"``: Eq. 16-17; DemoDICE-S uses ``"safe"``), trained for ``cfg["steps"]``
    steps with Adam (``cfg["lr"]``) through the offline :class:`~torchrl.trainers.Trainer`.
    ``cfg["gradient_penalty"]`` maps each positive role to its penalty coefficient (Table J: 10 for C_P, none
    for C_S). ``cfg["compile"]`` (default false) steps them with a :class:`CompiledStepper`.

    Examples:
        >>> from tensordict import TensorDict
        >>> from spoil_torchrl.data import DualDemoBuffers
        >>> episodes = TensorDict({"observation": torch.randn(8, 3), "action": torch.rand(8, 2) * 2 - 1,
        ...                        "episode": torch.arange(4).repeat_interleave(2),
        ...                        "is_init": torch.tensor([[True], [False]] * 4)}, [8])
        >>> roles = {"safe": [0, 1], "performant": [1, 2], "unlabeled": [0, 1, 2, 3]}
        >>> buffers = DualDemoBuffers(episodes, roles, batch_size=4)
        >>> context = BuildContext(buffers, observation_dim=3, action_dim=2, progress=False)
        >>> cfg = {"steps": 5, "lr": 1e-3, "hidden_cells": [16],
        ...        "gradient_penalty": {"performant": 10, "safe": 0}}  # Table J: a penalty on C_P only
        >>> discriminators = train_discriminators(cfg, context)  # C_P and C_S, 5 steps each
        >>> sorted(discriminators), type(discriminators["safe"]).__name__
        (['performant', 'safe'], 'PUDiscriminatorLoss')
        >>> log_ratio = discriminators["performant"].log_ratio_module("log_ratio_performant")
        >>> buffers.annotate("unlabeled", log_ratio)  # as SpoilDICE's pre-training does
        >>> buffers["unlabeled"].storage[:]["log_ratio_performant"].shape  # log r_P of every D_U transition
        torch.Size([8, 1])
    """
    penalties = cfg["gradient_penalty"]
    missing = [role for role in positives if role not in penalties]
    if missing:
        raise ValueError(f"discriminator.gradient_penalty has no coefficient for {missing}")
    losses = {
        f"disc_{role}": context.place(
            PUDiscriminatorLoss(
                make_discriminator(
                    context.observation_dim, context.action_dim, hidden_cells=tuple(cfg["hidden_cells"])
                ),
                positive=role,
                unlabeled=against,
                gradient_penalty=float(penalties[role]),
            )
        )
        for role in positives
    }
    optimizers = [adam(loss.parameters(), cfg["lr"]) for loss in losses.values()]
    stepper_class = CompiledStepper if cfg.get("compile", False) else MultiLossStepper
    trainer = offline_trainer(
        stepper_class(losses, optimizers),
        context.buffers.sample,
        total_steps=int(cfg["steps"]),
        steps_per_batch=min(100, int(cfg["steps"])),
        logger=context.logger,
        progress_bar=context.progress,
        progress_label=f"pre-training {', '.join(f'C_{role[0].upper()}' for role in positives)}",
    )
    trainer.train()
    return {name.removeprefix("disc_"): loss for name, loss in losses.items()}


def fit_support(
    loss: PUDiscriminatorLoss, buffers: DualDemoBuffers, role: str, kappa: float, out_key: str
) -> SupportEstimator:
    """Eq. (13) on ``role``'s discriminator: the kappa-quantile cut of its log-ratio over ``role``'s data.

    Examples:
        >>> from tensordict import TensorDict
        >>> from spoil_torchrl.data import DualDemoBuffers
        >>> episodes = TensorDict({"observation": torch.randn(8, 3), "action": torch.rand(8, 2) * 2 - 1,
        ...                        "episode": torch.arange(4).repeat_interleave(2),
        ...                        "is_init": torch.tensor([[True], [False]] * 4)}, [8])
        >>> roles = {"safe": [0, 1], "performant": [1, 2], "unlabeled": [0, 1, 2, 3]}
        >>> buffers = DualDemoBuffers(episodes, roles, batch_size=4)
        >>> context = BuildContext(buffers, observation_dim=3, action_dim=2, progress=False)
        >>> cfg = {"steps": 5, "lr": 1e-3, "hidden_cells": [16],
        ...        "gradient_penalty": {"performant": 10, "safe": 0}}  # Table J: a penalty on C_P only
        >>> safe_discriminator = train_discriminators(cfg, context)["safe"]
        >>> support = fit_support(safe_discriminator, buffers, "safe", kappa=0.5, out_key="safe_support")
        >>> support(buffers["safe"].storage[:].clone())["safe_support"].mean().item()  # >= 1 - kappa of D_S
        0.75
        >>> buffers.annotate("unlabeled", support)  # as SpoilDICE's pre-training marks D_U
        >>> buffers["unlabeled"].storage[:]["safe_support"].shape
        torch.Size([8, 1])
    """
    estimator = SupportEstimator(loss.frozen_network(), kappa=kappa, out_key=out_key).to(buffers.device)
    return estimator.fit(buffers[role].storage[:])


def frozen_networks(discriminators: Mapping[str, PUDiscriminatorLoss]) -> dict[str, torch.nn.Module]:
    """The frozen networks of trained discriminators (role -> loss), named ``C_<role>``: what a
    :class:`~spoil_torchrl.algorithms.base.Pretraining` keeps of them."""
    return {f"C_{role}": loss.frozen_network() for role, loss in discriminators.items()}
