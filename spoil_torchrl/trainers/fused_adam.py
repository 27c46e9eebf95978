"""PyTorch's fused Adam kernel for the compiled steps: switching an optimiser to it, and calling it straight.

A compiled step's update is one graph call, so the Python work around it is a visible part of the step:
``torch.optim.Adam.step`` rebuilds its lists of parameters, gradients and moments from the parameter groups on
every call, checks them and dispatches, before it reaches the one fused kernel (on the bench's SpoilDICE step, the
three optimisers' ``step`` calls took 0.6 ms of a 16.7 ms step, their kernels about a quarter of that).
:class:`FusedAdamSteps` calls the same kernel (``torch._fused_adam_`` / ``torch._fused_adamw_``) with the same
arguments in the same order, from lists read once: the parameters, the optimiser's state tensors and its groups'
settings stay the optimiser's, so learning-rate schedules, ``state_dict`` and resuming are unchanged, and the
numbers are ``Adam.step``'s bit for bit.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch.optim import Adam, AdamW
from torch.optim import optimizer as optim_module


def use_fused_adam(optimizers) -> None:
    """Switch the (exactly) ``torch.optim.Adam`` / ``AdamW`` optimizers among ``optimizers`` (or wrapped by a
    :class:`~spoil_torchrl.trainers.StepEvery`) to PyTorch's fused kernel, one kernel per step for all their
    parameters instead of a few per tensor (on CPU 0.17 ms against 0.49 ms for the default networks' twelve
    tensors). The update is Adam's; its floats differ from the default kernel's in the last bit, which is why the
    eager stepper keeps the default. Optimizers of other classes, or with parameters the fused kernel does not
    take (not floating point, or on a device without it), are left as they are.

    Examples:
        >>> optim = torch.optim.Adam([torch.nn.Parameter(torch.zeros(3))], lr=1e-3)
        >>> use_fused_adam([optim])
        >>> optim.param_groups[0]["fused"], optim.param_groups[0]["foreach"]
        (True, False)
    """
    try:  # a private helper of torch.optim: the devices with fused kernels
        from torch.optim.optimizer import _get_fused_kernels_supported_devices

        devices = _get_fused_kernels_supported_devices()
    except ImportError:
        devices = ["cpu", "cuda"]
    for optim in optimizers:
        optim = getattr(optim, "optimizer", optim)  # StepEvery holds one
        if type(optim) not in (Adam, AdamW):
            continue
        params = [p for group in optim.param_groups for p in group["params"]]
        if any(group["differentiable"] for group in optim.param_groups) or not all(
            p.is_floating_point() and p.device.type in devices for p in params
        ):
            continue
        for group in optim.param_groups:
            group["fused"], group["foreach"] = True, False
        optim.defaults.update(fused=True, foreach=False)


def _no_hooks(optim: torch.optim.Optimizer) -> bool:
    """Whether stepping ``optim`` runs no step hook of its own or of all optimisers."""
    global_hooks = (
        getattr(optim_module, "_global_optimizer_pre_hooks", {}),
        getattr(optim_module, "_global_optimizer_post_hooks", {}),
    )
    own = (getattr(optim, "_optimizer_step_pre_hooks", {}), getattr(optim, "_optimizer_step_post_hooks", {}))
    return not any(global_hooks) and not any(own)


def _direct_calls(optim) -> list[tuple] | None:
    """For a fused Adam / AdamW whose every parameter has its state (it has stepped once), with float settings,
    and which runs no hook and no gradient scaler: per parameter group, ``(group, params, exp_avgs, exp_avg_sqs,
    max_exp_avg_sqs, steps)``. ``None`` for any other optimiser (a :class:`~spoil_torchrl.trainers.StepEvery`
    included): it keeps its own ``step``."""
    if type(optim) not in (Adam, AdamW) or not _no_hooks(optim):
        return None
    if getattr(optim, "grad_scale", None) is not None or getattr(optim, "found_inf", None) is not None:
        return None
    calls = []
    for group in optim.param_groups:
        if not group.get("fused") or group["differentiable"] or group["capturable"]:
            return None
        if any(torch.is_tensor(x) for x in (group["lr"], *group["betas"])):
            return None  # tensor settings: Adam's own handling
        params = list(group["params"])
        states = [optim.state.get(p) for p in params]
        if not all(state and torch.is_tensor(state.get("step")) for state in states):
            return None
        if len({(p.device, p.dtype) for p in params}) > 1 or any(p.is_complex() for p in params):
            return None  # Adam groups such tensors by device and dtype: its order, not this one
        calls.append(
            (
                group,
                params,
                [s["exp_avg"] for s in states],
                [s["exp_avg_sq"] for s in states],
                [s["max_exp_avg_sq"] for s in states] if group["amsgrad"] else [],
                [s["step"] for s in states],
            )
        )
    return calls


def _current(optim, calls: list[tuple]) -> bool:
    """Whether ``calls`` (:func:`_direct_calls`) still hold ``optim``'s groups and state tensors: a
    ``load_state_dict`` or ``add_param_group`` made outside the stepper shows here (checked on each group's first
    parameter, a few dictionary lookups a step)."""
    if len(optim.param_groups) != len(calls):
        return False
    for group, (kept, params, exp_avgs, *_) in zip(optim.param_groups, calls, strict=True):
        state = optim.state.get(params[0]) if params else None
        if group is not kept or len(group["params"]) != len(params) or not state:
            return False
        if state.get("exp_avg") is not exp_avgs[0]:
            return False
    return True


class FusedAdamSteps:
    """Steps a stepper's optimisers, calling PyTorch's fused Adam kernel straight for those that run it.

    For every optimiser that :func:`use_fused_adam` switched to the fused kernel and that has stepped once
    through its own ``step`` (so its state exists), :meth:`step` makes the calls ``Adam.step`` makes on a CPU or
    GPU without a gradient scaler (the state's step counts incremented, then ``torch._fused_adam_`` over the
    group's parameters, gradients and moments, with the group's current settings), from lists kept between
    steps. Every other optimiser (another class, one with step hooks, a
    :class:`~spoil_torchrl.trainers.StepEvery`) steps through its own ``step``. Parameters without a gradient are
    skipped, as ``Adam.step`` skips them. An optimiser whose state or groups were replaced (``load_state_dict``,
    ``add_param_group``) has its lists read again at its next step; :meth:`reset` reads every optimiser's again.

    Examples:
        >>> p = torch.nn.Parameter(torch.ones(3))
        >>> optim = torch.optim.Adam([p], lr=0.1)
        >>> use_fused_adam([optim])
        >>> steps = FusedAdamSteps([optim])
        >>> for _ in range(3):
        ...     p.grad = torch.ones(3)
        ...     steps.step()
        >>> p.detach()  # three Adam steps of 0.1 against a constant gradient
        tensor([0.7000, 0.7000, 0.7000])
    """

    def __init__(self, optimizers: Sequence) -> None:
        self.optimizers = list(optimizers)
        self._calls: list[list[tuple] | None] | None = None

    def reset(self) -> None:
        """Read the optimisers' parameters and state again at the next step."""
        self._calls = None

    def step(self) -> None:
        """One step of every optimiser."""
        if self._calls is None:
            for optim in self.optimizers:  # the first step through Adam.step creates the state
                optim.step()
            self._calls = [_direct_calls(optim) for optim in self.optimizers]
            return
        for i, (optim, calls) in enumerate(zip(self.optimizers, self._calls, strict=True)):
            if calls is not None and not _current(optim, calls):  # its state or groups were replaced:
                optim.step()  # as after reset(), through Adam.step (which makes any state it lacks)
                self._calls[i] = _direct_calls(optim)
                continue
            if calls is None:
                optim.step()
                continue
            with torch.no_grad():
                for group, params, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps in calls:
                    _fused_step(group, params, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps)


def _fused_step(group: dict, params, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps) -> None:
    """``Adam.step``'s fused update of one parameter group: the parameters that have a gradient, with their
    moments and step counts, in the group's order."""
    grads = [p.grad for p in params]
    keep = [i for i, g in enumerate(grads) if g is not None]
    if not keep:
        return
    if len(keep) < len(params):
        params, grads, exp_avgs, exp_avg_sqs, steps = (
            [xs[i] for i in keep] for xs in (params, grads, exp_avgs, exp_avg_sqs, steps)
        )
        max_exp_avg_sqs = [max_exp_avg_sqs[i] for i in keep] if max_exp_avg_sqs else []
    beta1, beta2 = group["betas"]
    torch._foreach_add_(steps, 1)
    kernel = torch._fused_adamw_ if group.get("decoupled_weight_decay", False) else torch._fused_adam_
    kernel(
        params,
        grads,
        exp_avgs,
        exp_avg_sqs,
        max_exp_avg_sqs,
        steps,
        amsgrad=group["amsgrad"],
        lr=group["lr"],
        beta1=beta1,
        beta2=beta2,
        weight_decay=group["weight_decay"],
        eps=group["eps"],
        maximize=group["maximize"],
        grad_scale=None,
        found_inf=None,
    )
