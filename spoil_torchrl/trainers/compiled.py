"""The compiled update step: a main stage's whole update (every loss, the gradients, nu's gradient penalty with
its double backward) traced by ``torch.compile`` as one graph over plain tensors.

Every loss of the package is a :class:`~spoil_torchrl.objectives.pure.PureLoss`: its ``forward`` is
``terms(term_parameters(), inputs(tensordict))``, the equations living in ``terms`` as functions of plain
tensors. :class:`CompiledStepper` calls the same methods: each loss's ``inputs`` of the batch (eager: it reads
the tensordict and draws the penalty's random points, in the eager step's order), then one compiled function
that evaluates every loss's ``terms`` and differentiates the sum of their ``loss_*`` terms with
:func:`torch.func.grad_and_value`, which Dynamo traces whole. (A LossModule that puts its functional parameters
in place with tensordict's ``to_module`` cannot be traced: Dynamo skips any frame that does so; the pure
networks are called through :func:`torch.func.functional_call`.) The gradients are handed to the losses' own
optimisers, so parameters, optimiser state, schedules, checkpoints and resuming are those of the eager step.

What differs from the eager step, and why the numbers agree only to float tolerance:

* the compiler fuses and reorders float operations;
* Adam runs PyTorch's fused kernel (:func:`~spoil_torchrl.trainers.fused_adam.use_fused_adam`, called
  straight by :class:`~spoil_torchrl.trainers.fused_adam.FusedAdamSteps`), whose floats differ from the default
  kernel's in the last bit.

The random numbers (the penalty's interpolation points) are drawn outside the graph, in the eager step's order,
so a compiled run consumes the same random stream as an eager one; a compiled run is as deterministic as an
eager one.

Any loss with the ``inputs`` / ``terms`` / ``term_parameters`` methods compiles, a user's subclass included. A
stepper with a loss that has none, a network the pure form cannot call (``check_compilable``), or a step that
fails to compile trains eagerly, said once in the log.
"""

from __future__ import annotations

import itertools
import logging
import types
from collections.abc import Callable, Mapping

import torch
from tensordict import TensorDictBase
from torch import nn
from torch.func import grad_and_value
from torchrl.objectives import LossModule

from spoil_torchrl.objectives.pure import NotCompilable
from spoil_torchrl.trainers.fused_adam import FusedAdamSteps, use_fused_adam
from spoil_torchrl.trainers.offline import MultiLossStepper, scalar_outputs

log = logging.getLogger(__name__)


def pure_losses(losses: Mapping[str, LossModule]) -> dict[str, frozenset]:
    """For every loss of a step (in order), the keys the losses before it produce (what its ``inputs`` does not
    read from the batch), or :class:`~spoil_torchrl.objectives.pure.NotCompilable` naming the first loss that
    has no pure form or whose networks the compiled step cannot call."""
    earlier, out = frozenset(), {}
    for name, loss in losses.items():
        if not all(callable(getattr(loss, m, None)) for m in ("inputs", "terms", "term_parameters")):
            raise NotCompilable(f"{type(loss).__name__} has no inputs / terms split (not a PureLoss)")
        check = getattr(loss, "check_compilable", None)
        if check is not None:
            check()
        out[name] = earlier
        earlier = earlier | frozenset(getattr(loss, "produces", ()))
    return out


def update_gradients(losses: Mapping[str, LossModule]) -> Callable:
    """The uncompiled update of a step's losses: ``(params, inputs) -> (grads, (total, outputs))``, with
    ``params`` and ``inputs`` keyed by loss name (each loss's :meth:`term_parameters` detached, its
    :meth:`inputs` of a batch), the gradients of the summed ``loss_*`` terms in ``params``' structure, and each
    loss's outputs. A pure function: it can be compiled, or vmapped over a leading seed dimension of stacked
    parameters and inputs."""

    def total_loss(params, inputs):
        produced: dict = {}
        total, outputs = 0.0, {}
        for name, loss in losses.items():
            value, outputs[name] = loss.terms(params[name], inputs[name], produced)
            total = total + value
        return total, outputs

    return grad_and_value(total_loss, has_aux=True)


def step_inputs(losses: Mapping[str, LossModule], earlier: Mapping[str, frozenset], batch) -> dict:
    """Every loss's :meth:`inputs` of ``batch`` (in order: the random draws are the eager step's)."""
    return {name: loss.inputs(batch, earlier[name]) for name, loss in losses.items()}


def step_parameters(losses: Mapping[str, LossModule]) -> dict[str, dict[str, nn.Parameter]]:
    """Every loss's :meth:`term_parameters`, keyed by loss name."""
    return {name: loss.term_parameters() for name, loss in losses.items()}


def detached(parameters: Mapping[str, Mapping[str, torch.Tensor]]) -> dict[str, dict[str, torch.Tensor]]:
    """``parameters`` (loss name -> name -> parameter) detached: the arguments of :func:`update_gradients`."""
    return {name: {k: p.detach() for k, p in ps.items()} for name, ps in parameters.items()}


def set_gradients(parameters: Mapping[str, Mapping[str, torch.Tensor]], grads: Mapping | None) -> None:
    """Give every parameter its gradient from :func:`update_gradients`' result (the same structure); with
    ``grads=None``, drop them. A compiled step drops them once its optimisers have stepped, so their memory is
    free for the next step's graph (kept, they made the step 2-4 % slower on the bench's SpoilDICE step)."""
    for name, ps in parameters.items():
        for key, p in ps.items():
            p.grad = None if grads is None else grads[name][key]


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


def compile_update(fn: Callable, device: torch.device, mode: str | None = None) -> Callable:
    """``fn`` (an update of :func:`update_gradients`' form) compiled whole, as every compiled step is.

    With ``mode=None``: on a GPU, ``"reduce-overhead"`` (CUDA graphs); on a CPU, Inductor's default mode with its
    C++ wrapper (``cpp_wrapper``), which calls the graph's kernels from compiled C++ instead of a Python
    function. The kernels are the same, so the numbers are bit for bit those of the Python wrapper; the step
    runs a few per cent faster (``benchmarks/bench_losses.py``). A ``mode`` given is used as it is.

    Examples:
        >>> f = compile_update(lambda x: (x * 2).sum(), torch.device("cpu"))
        >>> float(f(torch.ones(3)))
        6.0
    """
    if mode is None and device.type == "cpu":
        return torch.compile(fn, fullgraph=True, dynamic=False, options={"cpp_wrapper": True})
    if mode is None and device.type == "cuda":
        mode = "reduce-overhead"
    return torch.compile(fn, mode=mode, fullgraph=True, dynamic=False)


class CompiledStepper(MultiLossStepper):
    """:class:`~spoil_torchrl.trainers.offline.MultiLossStepper` whose step is one ``torch.compile``\\ d graph.

    Same constructor, outputs (``<loss>.<entry>`` scalars), optimisers and state dict as the eager stepper; once
    its first step has compiled, its Adam optimisers run PyTorch's fused kernel (:func:`use_fused_adam`, called
    straight: :class:`~spoil_torchrl.trainers.fused_adam.FusedAdamSteps`). When
    a loss has no pure form (:func:`pure_losses`), or the first step fails to compile, it says so once (a
    warning of this module's logger) and steps eagerly from then on; that first step's random draws are undone
    first, so the run is the eager run.

    Args:
        losses, optimizers, schedulers: as for :class:`MultiLossStepper`.
        mode: ``torch.compile`` mode; ``None`` picks ``"reduce-overhead"`` (CUDA graphs) for parameters on a GPU
            and, on a CPU, the default mode with Inductor's C++ wrapper (:func:`compile_update`).

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
        self._parameters = None  # (step_parameters, their detached views), kept from step to step
        # once compiled: the fused Adam kernel called straight
        self._adam: FusedAdamSteps | None = None
        try:
            self._earlier: dict[str, frozenset] | None = pure_losses(self.losses)
        except NotCompilable as err:
            log.warning("train.compile: %s; the update step runs eagerly", err)
            self._earlier = None

    @classmethod
    def from_stepper(cls, stepper: MultiLossStepper, **kwargs) -> CompiledStepper:
        """The compiled version of an eager stepper (same losses, optimisers and schedules)."""
        return cls(stepper.losses, stepper.optimizers, stepper.schedulers, **kwargs)

    def _build(self, device: torch.device):
        update = _with_own_code(update_gradients(self.losses), f"compiled_update_{next(_STEPPERS)}")
        return compile_update(update, device, self.mode)

    def load_state_dict(self, state_dict) -> None:
        super().load_state_dict(state_dict)
        self._parameters = None  # loading copies into the same parameters; they are read again all the same
        if self._adam is not None:
            self._adam.reset()  # the optimisers' state tensors are new ones

    def _step_optimizers(self) -> None:
        if self._adam is None:
            super()._step_optimizers()
        else:
            self._adam.step()

    def step(self, trainer, sub_batch: TensorDictBase) -> TensorDictBase:
        if self._earlier is None:
            return super().step(trainer, sub_batch)
        if self._parameters is None:  # the parameter objects the optimisers step, and their detached views
            parameters = step_parameters(self.losses)
            self._parameters = (parameters, detached(parameters))
        parameters, plain = self._parameters
        device = next(p for ps in plain.values() for p in ps.values()).device
        rng = None if self.compiled else random_streams(device)
        inputs = step_inputs(self.losses, self._earlier, sub_batch)
        try:
            if self._fn is None:
                self._fn = self._build(device)
            grads, (_, outputs) = self._fn(plain, inputs)
        except Exception as err:
            if self.compiled:
                raise
            warn_not_compiled("the update step", err)
            self._earlier, self._fn = None, None
            set_random_streams(device, rng)
            return super().step(trainer, sub_batch)
        if not self.compiled:  # from now on Adam runs as one fused kernel, called straight
            use_fused_adam(self.optimizers)
            self._adam = FusedAdamSteps(self.optimizers)
        self.compiled = True
        self._apply_gradients(lambda: set_gradients(parameters, grads), replaces=True)
        set_gradients(parameters, None)
        return scalar_outputs(outputs)
