"""A compiled optimisation step: every loss of a :class:`MultiLossStepper` and its gradient as one compiled unit.

:class:`CompiledStepper` computes what :meth:`MultiLossStepper.step` computes -- the sum of the ``loss_*``
terms of its LossModules on one batch and the gradient of that sum with respect to every trainable parameter
-- as one function, ``torch.func.grad`` over the losses called with their parameters as plain tensors
(``TensorDict.to_module``), compiled with ``torch.compile``. The gradients are then handed to the *same*
optimisers (fused / foreach Adam), so LR schedules, optimisers that step less often and checkpoints are those of
the eager stepper. The double backward of the gradient penalties is no obstacle: they are written with
``torch.func`` (:func:`~spoil_torchrl.objectives.functional.input_gradient_norms`), which the compiler traces,
where ``torch.autograd.grad(create_graph=True)`` it cannot.

Random draws inside the losses (the gradient penalties' interpolation points) are compiled with inductor's
``fallback_random``, so they consume the global generator exactly as the eager step does: a compiled step
computes the eager step's numbers, up to float rounding (tested), and a seeded run stays reproducible.

Where the step cannot be compiled (a loss that does something the compiler rejects, a missing C++ compiler),
the first step says why in one log line and the stepper continues eagerly.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives import LossModule
from torchrl.trainers import Trainer

from spoil_torchrl.trainers.offline import MultiLossStepper

log = logging.getLogger(__name__)


def _scalars(outputs: Mapping[str, TensorDictBase]) -> dict[str, torch.Tensor]:
    """The one-element entries of every loss output, detached, as ``<loss name>.<entry>`` (for the logs)."""
    return {
        f"{name}.{key}": value.detach().float().mean()
        for name, out in outputs.items()
        for key, value in out.items()
        if value.numel() == 1
    }


class CompiledStepper(MultiLossStepper):
    """:class:`MultiLossStepper` whose losses and gradients are one compiled function (see module docstring).

    Args:
        losses, optimizers, schedulers: as for :class:`MultiLossStepper`.
        mode: ``torch.compile``'s mode; ``None`` picks ``"reduce-overhead"`` (CUDA graphs) when the parameters
            live on a GPU and the default otherwise.

    Examples:
        >>> from spoil_torchrl.modules import make_actor
        >>> from spoil_torchrl.objectives import WeightedBCLoss
        >>> loss = WeightedBCLoss(make_actor(3, 2, hidden_cells=(8,)), role="performant", weight=None)
        >>> stepper = CompiledStepper({"bc": loss}, [torch.optim.Adam(loss.parameters(), lr=1e-3)])
        >>> performant = TensorDict({"observation": torch.randn(16, 3), "action": torch.rand(16, 2) * 2 - 1}, [16])
        >>> batch = TensorDict({"performant": performant}, [])
        >>> sorted(stepper.step(None, batch).keys())
        ['bc.log_prob', 'bc.loss_actor', 'bc.weight_mean']
    """

    def __init__(
        self,
        losses: Mapping[str, LossModule],
        optimizers: Sequence[torch.optim.Optimizer],
        schedulers: Sequence[torch.optim.lr_scheduler.LRScheduler] = (),
        *,
        mode: str | None = None,
    ) -> None:
        super().__init__(losses, optimizers, schedulers)
        self.trainable = {
            name: {k: p for k, p in loss.named_parameters() if p.requires_grad}
            for name, loss in self.losses.items()
        }
        self.frozen = {
            name: {
                k: v
                for k, v in TensorDict.from_module(loss).flatten_keys(".").items()
                if k not in self.trainable[name]
            }
            for name, loss in self.losses.items()
        }
        first = next(p for params in self.trainable.values() for p in params.values())
        self.mode = mode if mode is not None else ("reduce-overhead" if first.is_cuda else None)
        # fallback_random: the compiled step draws the eager step's random numbers (inductor's own option;
        # torch.compile takes either a mode or options)
        options = {"fallback_random": True} if self.mode is None else None
        self.compiled = torch.compile(
            torch.func.grad(self._total, has_aux=True), mode=self.mode, options=options
        )
        self.eager_reason: str | None = None
        self._steps = 0

    @classmethod
    def from_stepper(cls, stepper: MultiLossStepper, **kwargs) -> CompiledStepper:
        """The compiled twin of ``stepper`` (same losses, optimisers and schedulers)."""
        return cls(stepper.losses, stepper.optimizers, stepper.schedulers, **kwargs)

    def _total(
        self,
        trainable: dict[str, dict[str, torch.Tensor]],
        frozen: dict[str, dict[str, torch.Tensor]],
        batch: TensorDictBase,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The sum of every ``loss_*`` term with the parameters ``trainable`` (and the logged scalars)."""
        outputs = {}
        for name, loss in self.losses.items():
            params = TensorDict({**trainable[name], **frozen[name]}, []).unflatten_keys(".")
            with params.to_module(loss):
                outputs[name] = loss(batch)
        total = sum(
            value for out in outputs.values() for key, value in out.items() if key.startswith("loss_")
        )
        return total, _scalars(outputs)

    def step(self, trainer: Trainer | None, sub_batch: TensorDictBase) -> TensorDictBase:
        if self.eager_reason is not None:
            return super().step(trainer, sub_batch)
        values = {name: {k: p.detach() for k, p in params.items()} for name, params in self.trainable.items()}
        try:
            grads, scalars = self.compiled(values, self.frozen, sub_batch)
        except Exception as err:  # noqa: BLE001 - any compiler failure: say it once, train eagerly
            if self._steps:
                raise
            self.eager_reason = f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
            log.warning(
                f"train.compile: the step could not be compiled ({self.eager_reason}); training eagerly"
            )
            return super().step(trainer, sub_batch)
        self._steps += 1
        for optimizer in self.optimizers:
            optimizer.zero_grad(set_to_none=True)
        for name, params in self.trainable.items():
            for key, param in params.items():
                param.grad = grads[name][key]
        for optimizer in self.optimizers:
            optimizer.step()
        for scheduler in self.schedulers:
            scheduler.step()
        return TensorDict(scalars, batch_size=[])


def compile_stepper(stepper: MultiLossStepper, enabled: bool | str) -> MultiLossStepper:
    """``stepper`` itself (``enabled`` false) or its :class:`CompiledStepper` twin (``True`` / ``"auto"``)."""
    if not enabled:
        return stepper
    return CompiledStepper.from_stepper(stepper)
