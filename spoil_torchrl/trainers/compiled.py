"""The compiled update step: a main stage's whole update (every loss, the gradients, nu's gradient penalty with
its double backward) traced by ``torch.compile`` as one graph over plain tensors.

Why plain tensors. A LossModule puts its functional parameters in place with tensordict's ``to_module``, and
Dynamo skips any frame that does so: compiling the LossModules themselves runs them eagerly (measured, see
CONTRIBUTING.md). :class:`CompiledStepper` therefore reads each loss's networks and parameters, evaluates the
same equation functions the LossModule calls (:func:`~spoil_torchrl.objectives.spoildice.spoildice_losses`,
:func:`~spoil_torchrl.objectives.weighted_bc.weighted_bc_outputs`, ...) through
:func:`torch.func.functional_call`, and differentiates the sum of the ``loss_*`` terms with
:func:`torch.func.grad_and_value`, which Dynamo traces whole. The gradients are handed to the losses' own
optimisers, so parameters, optimiser state, schedules, checkpoints and resuming are those of the eager step.

What differs from the eager step, and why the numbers agree only to float tolerance:

* a DICE dual's state network (nu, COptiDICE's chi) is evaluated on the penalty's points (whose first rows are
  the current states, see :func:`~spoil_torchrl.objectives.functional.penalty_points`) once, for both the dual
  and the penalty, instead of on the current states a second time: the same values, one forward pass of the
  batch fewer;
* the compiler fuses and reorders float operations;
* Adam runs PyTorch's fused kernel (:func:`use_fused_adam`), whose floats differ from the default kernel's in
  the last bit.

The random numbers (the penalty's interpolation points) are drawn outside the graph, in the eager step's order,
so a compiled run consumes the same random stream as an eager one; a compiled run is as deterministic as an
eager one.

Every loss of the package has a compiled form, registered in ``COMPILED_FORMS``
(:mod:`~spoil_torchrl.trainers.compiled_forms`; CONTRIBUTING.md, "How to add a loss"). A stepper with a loss
that has none, a network the plain-tensor path cannot read, or a step that fails to compile trains eagerly,
said once in the log.
"""

from __future__ import annotations

import itertools
import logging
import types
from collections.abc import Callable, Mapping
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn
from torch.func import grad_and_value
from torchrl.objectives import LossModule

from spoil_torchrl.trainers.compiled_forms import NotCompilable, compiled_forms
from spoil_torchrl.trainers.offline import MultiLossStepper, scalar_outputs

log = logging.getLogger(__name__)


def update_gradients(forms: Mapping[str, Any]) -> Callable:
    """The uncompiled update of a step's compiled forms: ``(params, inputs) -> (grads, (total, outputs))``, with
    ``params`` and ``inputs`` keyed by loss name (each loss's :meth:`parameters` detached, its :meth:`inputs` of a
    batch), the gradients of the summed ``loss_*`` terms in ``params``' structure, and each loss's outputs. A pure
    function: it can be compiled, or vmapped over a leading seed dimension of stacked parameters and inputs."""

    def total_loss(params, inputs):
        produced: dict = {}
        total, outputs = 0.0, {}
        for name, form in forms.items():
            loss, outputs[name] = form(params[name], inputs[name], produced)
            total = total + loss
        return total, outputs

    return grad_and_value(total_loss, has_aux=True)


def detached(parameters: Mapping[str, Mapping[str, torch.Tensor]]) -> dict[str, dict[str, torch.Tensor]]:
    """``parameters`` (loss name -> name -> parameter) detached: the arguments of :func:`update_gradients`."""
    return {name: {k: p.detach() for k, p in ps.items()} for name, ps in parameters.items()}


def set_gradients(parameters: Mapping[str, Mapping[str, torch.Tensor]], grads: Mapping) -> None:
    """Give every parameter its gradient from :func:`update_gradients`' result (the same structure)."""
    for name, ps in parameters.items():
        for key, p in ps.items():
            p.grad = grads[name][key]


def use_fused_adam(optimizers) -> None:
    """Switch the (exactly) ``torch.optim.Adam`` / ``AdamW`` optimizers among ``optimizers`` (or wrapped by a
    :class:`~spoil_torchrl.trainers.StepEvery`) to PyTorch's fused kernel, one kernel per step for all their
    parameters instead of a few per tensor (on CPU 0.17 ms against 0.49 ms for the default networks' twelve
    tensors). The update is Adam's; its floats differ from the default kernel's in the last bit, which is why the
    eager stepper keeps the default. Optimizers of other classes, or with parameters the fused kernel does not
    take (not floating point, or on a device without it), are left as they are.

    Examples:
        >>> optim = torch.optim.Adam([nn.Parameter(torch.zeros(3))], lr=1e-3)
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
        if type(optim) not in (torch.optim.Adam, torch.optim.AdamW):
            continue
        params = [p for group in optim.param_groups for p in group["params"]]
        if any(group["differentiable"] for group in optim.param_groups) or not all(
            p.is_floating_point() and p.device.type in devices for p in params
        ):
            continue
        for group in optim.param_groups:
            group["fused"], group["foreach"] = True, False
        optim.defaults.update(fused=True, foreach=False)


def warn_not_compiled(what: str, err: Exception) -> None:
    """Say once, in one line, that ``what`` did not compile (the error's type and first line) and runs eagerly."""
    text = str(err).strip()
    log.warning(
        "train.compile: %s did not compile (%s: %s); it runs eagerly",
        what,
        type(err).__name__,
        text.splitlines()[0] if text else "",
    )


_STEPPERS = itertools.count()


def _with_own_code(fn: Callable, name: str) -> Callable:
    """``fn`` called through a function whose code object is its own.

    Dynamo keeps its compiled graphs per code object and recompiles at most ``recompile_limit`` (8) times per
    code object before it gives up; every stepper's update would otherwise enter through the same code object
    (torch.func's ``grad_and_value`` wrapper), so the ninth stepper of a process would no longer compile. With a
    code object of its own each stepper has its own cache, freed with the stepper.

    Examples:
        >>> f = _with_own_code(abs, "absolute")
        >>> f(-2), f.__code__ is _with_own_code(abs, "absolute").__code__
        (2, False)
    """

    def call(*args):
        return fn(*args)

    code = call.__code__.replace(co_name=name, co_qualname=name)
    return types.FunctionType(code, call.__globals__, name, None, call.__closure__)


def random_streams(device: torch.device) -> tuple:
    """The state of the generators a step may draw from: the CPU's, and the GPU's when the parameters live on
    one (``None`` otherwise)."""
    return torch.get_rng_state(), torch.cuda.get_rng_state(device) if device.type == "cuda" else None


def set_random_streams(device: torch.device, state: tuple) -> None:
    """Restore what :func:`random_streams` returned."""
    torch.set_rng_state(state[0])
    if state[1] is not None:
        torch.cuda.set_rng_state(state[1], device)


class CompiledStepper(MultiLossStepper):
    """:class:`~spoil_torchrl.trainers.offline.MultiLossStepper` whose step is one ``torch.compile``\\ d graph.

    Same constructor, outputs (``<loss>.<entry>`` scalars), optimisers and state dict as the eager stepper; once
    its first step has compiled, its Adam optimisers run PyTorch's fused kernel (:func:`use_fused_adam`). When
    a loss has no compiled form, or the first step fails to compile, it says so once (a warning of this module's
    logger) and steps eagerly from then on; that first step's random draws are undone first, so the run is the
    eager run.

    Args:
        losses, optimizers, schedulers: as for :class:`MultiLossStepper`.
        mode: ``torch.compile`` mode; ``None`` picks ``"reduce-overhead"`` (CUDA graphs) for parameters on a GPU
            and the default mode otherwise.

    Examples:
        >>> from tensordict import TensorDict
        >>> from spoil_torchrl.modules import make_actor
        >>> from spoil_torchrl.objectives import WeightedBCLoss
        >>> loss = WeightedBCLoss(make_actor(3, 2, hidden_cells=(8,)), role="performant")
        >>> stepper = CompiledStepper({"actor": loss}, [torch.optim.Adam(loss.parameters(), lr=1e-3)])
        >>> batch = TensorDict({"performant": TensorDict({"observation": torch.randn(16, 3),
        ...                                               "action": torch.rand(16, 2) * 2 - 1}, [16])}, [])
        >>> sorted(stepper.step(None, batch).keys())
        ['actor.log_prob', 'actor.loss_actor', 'actor.weight_mean']
    """

    def __init__(
        self,
        losses: Mapping[str, LossModule],
        optimizers,
        schedulers=(),
        *,
        mode: str | None = None,
    ) -> None:
        super().__init__(losses, optimizers, schedulers)
        self.mode = mode
        self.compiled = False  # True once a step has run compiled
        self._fn = None
        try:
            self._forms: dict[str, Any] | None = compiled_forms(self.losses)
        except NotCompilable as err:
            log.warning("train.compile: %s; the update step runs eagerly", err)
            self._forms = None

    @classmethod
    def from_stepper(cls, stepper: MultiLossStepper, **kwargs) -> CompiledStepper:
        """The compiled version of an eager stepper (same losses, optimisers and schedules)."""
        return cls(stepper.losses, stepper.optimizers, stepper.schedulers, **kwargs)

    @property
    def forms(self) -> dict[str, Any] | None:
        """The losses' compiled forms (``None`` once the stepper runs eagerly)."""
        return self._forms

    def _parameters(self) -> dict[str, dict[str, nn.Parameter]]:
        return {name: form.parameters() for name, form in self._forms.items()}

    def _build(self, device: torch.device):
        mode = self.mode or ("reduce-overhead" if device.type == "cuda" else None)
        update = _with_own_code(update_gradients(self._forms), f"compiled_update_{next(_STEPPERS)}")
        return torch.compile(update, mode=mode, fullgraph=True, dynamic=False)

    def step(self, trainer, sub_batch: TensorDictBase) -> TensorDictBase:
        if self._forms is None:
            return super().step(trainer, sub_batch)
        parameters = self._parameters()
        device = next(p for ps in parameters.values() for p in ps.values()).device
        rng = random_streams(device)
        inputs = {name: form.inputs(sub_batch) for name, form in self._forms.items()}
        try:
            if self._fn is None:
                self._fn = self._build(device)
            grads, (_, outputs) = self._fn(detached(parameters), inputs)
        except Exception as err:
            if self.compiled:
                raise
            warn_not_compiled("the update step", err)
            self._forms, self._fn = None, None
            set_random_streams(device, rng)
            return super().step(trainer, sub_batch)
        if not self.compiled:  # the step compiles: from now on Adam runs as one fused kernel too
            use_fused_adam(self.optimizers)
        self.compiled = True
        self._apply_gradients(lambda: set_gradients(parameters, grads))
        return scalar_outputs(outputs)
