"""The estimated supports of several safety constraints (``docs/several_constraints.md``): one PU discriminator
C_S^k per safe set ``safe_<name>`` against D_U and one kappa cut each (Eq. 13 on D_S^k), what SpoilDICE's
stage 1 and FBC's filter assemble when the dataset names ``dataset.constraints``."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch

from spoil_torchrl.algorithms.base import BuildContext, fit_support, train_discriminators
from spoil_torchrl.data.constraint_costs import CONSTRAINT_ROLE_PREFIX
from spoil_torchrl.objectives import PUDiscriminatorLoss
from spoil_torchrl.objectives.spoildice import check_supports_intersect


def constraint_roles_of(buffers) -> list[str]:
    """The roles of the per-constraint safe sets in ``buffers`` (``safe_<name>``, in the dataset's order)."""
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
    roles in common are refused (:func:`~spoil_torchrl.objectives.check_supports_intersect`).

    Returns the discriminators (role -> loss), the indicator columns, and per-constraint diagnostics
    (``support_share_<role>_<name>``, ``support_threshold_<name>``; ``support_share_<role>`` of the
    intersection)."""
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
    for target in stacked:
        buffers.annotate(target, "safe_support", lambda td: torch.cat([td[c] for c in columns], -1))
    for target in intersected:
        buffers.annotate(
            target, "safe_support", lambda td: torch.cat([td[c] for c in columns], -1).prod(-1, keepdim=True)
        )
    first = (*stacked, *intersected)[0]
    data = buffers[first].storage[:]
    check_supports_intersect(
        torch.cat([data[c] for c in columns], -1), f"the annotated {first}'s safe supports"
    )
    for target in (*stacked, *intersected):
        inside = buffers[target].storage[:]["safe_support"].prod(-1).float().mean()
        diagnostics[f"support_share_{target}"] = float(inside)
    return discriminators, columns, diagnostics
