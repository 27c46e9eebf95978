"""The estimated supports of several safety constraints (``docs/several_constraints.md``): one PU discriminator
C_S^k per safe set ``safe_<name>`` against D_U and one kappa cut each (Eq. 13 on D_S^k), what SpoilDICE's
stage 1 and FBC's filter assemble when the dataset names ``dataset.constraints``."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch

from spoil_torchrl.algorithms.base import BuildContext
from spoil_torchrl.algorithms.discriminators import fit_support, train_discriminators
from spoil_torchrl.data.constraint_costs import CONSTRAINT_ROLE_PREFIX
from spoil_torchrl.objectives import PUDiscriminatorLoss
from spoil_torchrl.objectives.support import check_supports_intersect


def constraint_roles_of(buffers) -> list[str]:
    """The roles of the per-constraint safe sets in ``buffers`` (``safe_<name>``, in the dataset's order).

    Examples:
        >>> from spoil_torchrl.data import DualDemoBuffers
        >>> from tensordict import TensorDict
        >>> episodes = TensorDict({"observation": torch.zeros(3, 1), "episode": torch.arange(3),
        ...                        "is_init": torch.ones(3, 1, dtype=torch.bool)}, [3])
        >>> roles = {"safe": [0], "safe_x_wall": [1], "safe_y_wall": [2], "unlabeled": [0, 1, 2]}
        >>> constraint_roles_of(DualDemoBuffers(episodes, roles, batch_size=1))
        ['safe_x_wall', 'safe_y_wall']
    """
    return [role for role in buffers.roles if role.startswith(CONSTRAINT_ROLE_PREFIX)]


def fit_constraint_supports(
    cfg: Mapping[str, Any],
    context: BuildContext,
    *,
    stacked: Sequence[str] = (),
    intersected: Sequence[str] = (),
    positives: Sequence[str] = (),
) -> tuple[dict[str, PUDiscriminatorLoss], list[str], dict[str, float]]:
    """One C_S^k per safe set of the buffers (with C_S's gradient penalty) trained beside the discriminators of
    ``positives`` (e.g. ``("performant",)``), one kappa cut per constraint, and each support's indicator annotated
    as ``safe_support_<name>`` on every role of ``stacked`` and ``intersected``. ``safe_support`` is then the K
    indicators ``[n, K]`` on the ``stacked`` roles (SpoilDICE's D_U: one lambda_k each) and their product, the
    indicator of the intersection, on the ``intersected`` ones. Supports with no transition of the first of these
    roles in common are refused (:func:`~spoil_torchrl.objectives.support.check_supports_intersect`).

    Returns the discriminators (role -> loss), the indicator columns, and per-constraint diagnostics
    (``support_share_<role>_<name>``, ``support_threshold_<name>``; ``support_share_<role>`` of the
    intersection).

    Examples:
        >>> from spoil_torchrl.data import DualDemoBuffers
        >>> from tensordict import TensorDict
        >>> _ = torch.manual_seed(0)
        >>> n = 40  # 4 episodes of 10 steps; safe set a holds episode 0, safe set b episode 1
        >>> episodes = TensorDict({"observation": torch.randn(n, 3), "action": torch.randn(n, 2),
        ...                        "episode": torch.arange(n) // 10,
        ...                        "is_init": (torch.arange(n) % 10 == 0).unsqueeze(-1)}, [n])
        >>> roles = {"safe_a": [0], "safe_b": [1], "performant": [2], "unlabeled": [0, 1, 2, 3]}
        >>> context = BuildContext(DualDemoBuffers(episodes, roles, batch_size=8), 3, 2, progress=False)
        >>> cfg = {"kappa": 0.1, "discriminator": {"hidden_cells": [8], "gradient_penalty": {"safe": 0.0},
        ...                                        "lr": 1e-3, "steps": 2}}
        >>> _, columns, diagnostics = fit_constraint_supports(cfg, context, intersected=("performant",))
        >>> columns, context.buffers["performant"].storage[:]["safe_support"].shape
        (['safe_support_a', 'safe_support_b'], torch.Size([10, 1]))
        >>> diagnostics["support_share_performant"] <= diagnostics["support_share_performant_a"]
        True
    """
    buffers = context.buffers
    roles = constraint_roles_of(buffers)
    penalties = dict(cfg["discriminator"]["gradient_penalty"])
    settings = dict(cfg["discriminator"]) | {
        "gradient_penalty": penalties | dict.fromkeys(roles, penalties["safe"])
    }
    discriminators = train_discriminators(settings, context, positives=(*positives, *roles))
    columns, diagnostics = [], {}
    for role in roles:
        name = role.removeprefix(CONSTRAINT_ROLE_PREFIX)
        key = f"safe_support_{name}"
        support = fit_support(discriminators[role], buffers, role, float(cfg["kappa"]), key)
        for target in (*stacked, *intersected):
            buffers.annotate(target, support)
            share = float(buffers[target].storage[:][key].float().mean())
            diagnostics[f"support_share_{target}_{name}"] = share
        columns.append(key)
        diagnostics[f"support_threshold_{name}"] = float(support.threshold)

    def indicators(td):  # the K indicators side by side, [n, K]
        return torch.cat([td[c] for c in columns], -1)

    for target in stacked:
        buffers.annotate(target, "safe_support", indicators)
    for target in intersected:
        buffers.annotate(target, "safe_support", lambda td: indicators(td).prod(-1, keepdim=True))
    first = (*stacked, *intersected)[0]
    check_supports_intersect(indicators(buffers[first].storage[:]), f"the annotated {first}'s safe supports")
    for target in (*stacked, *intersected):
        inside = buffers[target].storage[:]["safe_support"].prod(-1).float().mean()
        diagnostics[f"support_share_{target}"] = float(inside)
    return discriminators, columns, diagnostics
