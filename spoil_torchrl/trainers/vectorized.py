"""Several seeds trained in one process: their parameters stacked along a leading seed dimension, the update
step vmapped over it and compiled once.

:class:`VectorizedStepper` takes one stepper per seed (the same algorithm, built the same way, each with its own
initial weights) and steps all of them at once. The update of a step is the compiled step's pure function
(:func:`~spoil_torchrl.trainers.compiled.update_gradients` of the losses' ``terms``) under
:func:`torch.vmap`: every parameter becomes one tensor ``[seeds, ...]``, every input one tensor ``[seeds,
batch, ...]`` (each seed on its own batch), and one optimiser per seed-optimiser steps the stacked parameters.
Adam and SGD are elementwise, so one optimiser over stacked parameters is one optimiser per seed.

Each seed keeps its own random stream (the gradient penalty's interpolation points are drawn from it, in the
single-seed step's order), so seed ``s`` of a vectorised run draws what a run of seed ``s`` alone draws; its
numbers agree with that run's to float tolerance (the vmapped graph fuses differently), and the run is as
deterministic as a single one.

The per-seed steppers stay the source of truth between steps: :meth:`VectorizedStepper.sync` writes the
stacked parameters and optimiser states back into them, so each seed's evaluation, diagnostics, policy file and
checkpoint are exactly those of a single-seed run, and a seed's checkpoint resumes as a single-seed run.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn

from spoil_torchrl.objectives.pure import NotCompilable
from spoil_torchrl.trainers.compiled import (
    _with_own_code,
    compile_update,
    detached,
    pure_losses,
    random_streams,
    set_gradients,
    set_random_streams,
    step_inputs,
    step_parameters,
    update_gradients,
    warn_not_compiled,
)
from spoil_torchrl.trainers.fused_adam import FusedAdamSteps, use_fused_adam
from spoil_torchrl.trainers.offline import MultiLossStepper, StepEvery


class NotVectorizable(ValueError):
    """The seeds' steppers cannot be stacked (another structure, other settings, a schedule); says why."""


def _settings(loss: nn.Module, per_seed: frozenset) -> dict[str, Any]:
    """The plain settings of a loss (numbers, strings, flags, its tensor keys) that its ``terms`` read as
    constants, i.e. all but those it takes per seed from its inputs (``per_seed``)."""
    plain = (bool, int, float, str, type(None))
    out = {k: v for k, v in vars(loss).items() if isinstance(v, plain) and k not in per_seed}
    keys = getattr(loss, "tensor_keys", None)
    if keys is not None:
        out["tensor_keys"] = str(keys)
    return out


def _check_same(losses: Sequence[Mapping[str, nn.Module]], seeds: Sequence[int]) -> None:
    """Every seed's losses are the first seed's up to their parameters (and what a loss takes per seed)."""
    first = losses[0]
    for seed, seed_losses in zip(seeds[1:], losses[1:], strict=True):
        if list(seed_losses) != list(first):
            raise NotVectorizable(f"seed {seed} trains other losses ({list(seed_losses)} vs {list(first)})")
        for name, loss in seed_losses.items():
            ref = first[name]
            if type(loss) is not type(ref):
                raise NotVectorizable(f"seed {seed}: loss {name!r} is a {type(loss).__name__}")
            shapes = {k: tuple(p.shape) for k, p in loss.term_parameters().items()}
            if shapes != {k: tuple(p.shape) for k, p in ref.term_parameters().items()}:
                raise NotVectorizable(f"seed {seed}: loss {name!r} has other parameter shapes")
            per_seed = frozenset(getattr(loss, "per_seed", ()))
            mine, theirs = _settings(loss, per_seed), _settings(ref, per_seed)
            differ = sorted(k for k in mine.keys() | theirs.keys() if mine.get(k) != theirs.get(k))
            if differ:
                raise NotVectorizable(
                    f"seed {seed}: {type(loss).__name__} {name!r} has other settings ({', '.join(differ)})"
                )


def _inner(optimizer):
    return getattr(optimizer, "optimizer", optimizer)  # StepEvery holds one


class _StackedOptimizer:
    """One optimiser of every seed (the same class and hyper-parameters) as one optimiser over the stacked
    parameters; its state is the seeds' states stacked (``step`` counts are shared: the seeds step together)."""

    def __init__(self, per_seed: Sequence, stacked_of: Sequence[Mapping[int, torch.Tensor]]) -> None:
        first = per_seed[0]
        inner = [_inner(o) for o in per_seed]
        for o in inner[1:]:
            same_groups = [{k: v for k, v in g.items() if k != "params"} for g in o.param_groups] == [
                {k: v for k, v in g.items() if k != "params"} for g in inner[0].param_groups
            ]
            if type(o) is not type(inner[0]) or not same_groups:
                raise NotVectorizable("the seeds' optimisers differ in class or hyper-parameters")
        if isinstance(first, StepEvery) and len({o.calls for o in per_seed}) != 1:
            raise NotVectorizable("the seeds' StepEvery optimisers are at different calls")
        self.per_seed, self.stacked_of = list(per_seed), list(stacked_of)
        groups = []
        for group in inner[0].param_groups:
            params = [stacked_of[0][id(p)] for p in group["params"]]
            groups.append({**{k: v for k, v in group.items() if k != "params"}, "params": params})
        optimizer = type(inner[0])(groups)
        self.optimizer = StepEvery(optimizer, first.interval) if isinstance(first, StepEvery) else optimizer
        self.load_from_seeds()

    def _pairs(self, seed_index: int):
        """(the seed's parameter, the stacked parameter) of every parameter of this optimiser."""
        inner = _inner(self.per_seed[seed_index])
        for group in inner.param_groups:
            for p in group["params"]:
                yield p, self.stacked_of[seed_index][id(p)]

    def load_from_seeds(self) -> None:
        """The stacked state from the seeds' optimiser states."""
        stacked = _inner(self.optimizer)
        stacked.state.clear()
        states = [list(self._pairs(i)) for i in range(len(self.per_seed))]
        for i, (_, target) in enumerate(states[0]):
            seed_states = [
                _inner(o).state.get(pairs[i][0], {}) for o, pairs in zip(self.per_seed, states, strict=True)
            ]
            if not seed_states[0]:
                continue
            merged = {}
            for key, value in seed_states[0].items():
                if torch.is_tensor(value) and key != "step":
                    merged[key] = torch.stack([s[key] for s in seed_states]).to(target.device)
                else:
                    if any(not _equal(s[key], value) for s in seed_states):
                        raise NotVectorizable(f"the seeds' optimisers are at different {key!r}")
                    merged[key] = value.clone() if torch.is_tensor(value) else value
            stacked.state[target] = merged
        if isinstance(self.optimizer, StepEvery):
            self.optimizer.calls = self.per_seed[0].calls

    def write_to_seeds(self) -> None:
        """Each seed's optimiser state from its slice of the stacked state."""
        stacked = _inner(self.optimizer)
        for i, o in enumerate(self.per_seed):
            state = _inner(o).state
            for p, target in self._pairs(i):
                merged = stacked.state.get(target)
                if not merged:
                    continue
                state[p] = {
                    k: (v[i].clone() if torch.is_tensor(v) and k != "step" else _copy(v))
                    for k, v in merged.items()
                }
            if isinstance(o, StepEvery):
                o.calls = self.optimizer.calls


def _equal(a, b) -> bool:
    return torch.equal(a, b) if torch.is_tensor(a) else a == b


def _copy(value):
    return value.clone() if torch.is_tensor(value) else value


def _check_steppers(steppers: Sequence, rng_states: Sequence, seeds: Sequence[int] | None) -> list[int]:
    """The seeds' names (default ``0, 1, ...``), once there is a stepper, a name and a random state per seed and
    no learning-rate schedule."""
    if not steppers:
        raise ValueError("VectorizedStepper needs at least one stepper")
    seeds = list(range(len(steppers))) if seeds is None else list(seeds)
    if len(seeds) != len(steppers) or len(rng_states) != len(steppers):
        raise ValueError("one seed name and one random state per stepper")
    if any(s.schedulers for s in steppers):
        raise NotVectorizable("learning-rate schedules are not vectorised")
    return seeds


def _stack_optimizers(
    steppers: Sequence[MultiLossStepper], params: Mapping[str, Mapping[str, torch.Tensor]]
) -> list[_StackedOptimizer]:
    """Each optimiser of the seeds (the ``j``-th of every seed) as one optimiser over the stacked parameters
    ``params`` (loss name -> parameter name -> stacked leaf)."""
    stacked_of = [  # per seed: id(the seed's parameter) -> the stacked parameter
        {id(p): params[name][key] for name, ps in step_parameters(s.losses).items() for key, p in ps.items()}
        for s in steppers
    ]
    if len({len(s.optimizers) for s in steppers}) != 1:
        raise NotVectorizable("the seeds have different numbers of optimisers")
    for i in range(len(steppers)):
        stepped = (p for o in steppers[i].optimizers for g in _inner(o).param_groups for p in g["params"])
        if any(id(p) not in stacked_of[i] for p in stepped):
            raise NotVectorizable("an optimiser steps a parameter that no loss's terms differentiate")
    return [
        _StackedOptimizer([s.optimizers[j] for s in steppers], stacked_of)
        for j in range(len(steppers[0].optimizers))
    ]


class VectorizedStepper(MultiLossStepper):
    """The steps of several seeds' steppers as one vmapped (and compiled) update.

    Args:
        steppers: one :class:`~spoil_torchrl.trainers.MultiLossStepper` per seed, the same losses (up to their
            parameters) and optimisers; learning-rate schedules are not supported.
        rng_states: each seed's random streams where that seed's single run would start its main stage
            (:func:`~spoil_torchrl.trainers.compiled.random_streams`, or just ``torch.get_rng_state()`` for
            parameters on the CPU); the step draws each seed's random numbers from its own streams.
        seeds: the seeds' names, for messages and output (default ``0, 1, ...``).
        compile: compile the vmapped update (``torch.compile``); ``False``, or a step that fails to compile,
            runs it eagerly (said once in the log).
        mode: ``torch.compile`` mode (``None``: ``"reduce-overhead"`` for parameters on a GPU).

    :meth:`step` takes one batch per seed (a sequence, or :meth:`batch`'s TensorDict of them) and returns the
    ``<loss>.<entry>`` scalars of every seed as tensors of shape ``[seeds]``. Call :meth:`sync` before reading a
    seed's networks or optimisers.

    Examples:
        >>> from spoil_torchrl.modules import make_actor
        >>> from spoil_torchrl.objectives import WeightedBCLoss
        >>> def stepper():
        ...     loss = WeightedBCLoss(make_actor(3, 2, hidden_cells=(8,)), role="performant")
        ...     return MultiLossStepper({"actor": loss}, [torch.optim.Adam(loss.parameters(), lr=1e-3)])
        >>> seeds = VectorizedStepper([stepper(), stepper()], [torch.get_rng_state()] * 2, compile=False)
        >>> def batch():
        ...     return TensorDict({"performant": TensorDict({"observation": torch.randn(16, 3),
        ...                                                   "action": torch.rand(16, 2) * 2 - 1}, [16])}, [])
        >>> seeds.step(None, [batch(), batch()])["actor.loss_actor"].shape
        torch.Size([2])
    """

    def __init__(
        self,
        steppers: Sequence[MultiLossStepper],
        rng_states: Sequence[torch.Tensor | tuple],
        *,
        seeds: Sequence[int] | None = None,
        compile: bool = True,
        mode: str | None = None,
    ) -> None:
        self.seeds = _check_steppers(steppers, rng_states, seeds)
        try:
            self.earlier = [pure_losses(s.losses) for s in steppers]
        except NotCompilable as err:
            raise NotVectorizable(str(err)) from None
        _check_same([s.losses for s in steppers], self.seeds)
        self.steppers = list(steppers)
        names = steppers[0].losses
        self.params = {  # loss name -> parameter name -> stacked leaf [seeds, ...]
            name: {key: self._seeds_values(name, key) for key in names[name].term_parameters()}
            for name in names
        }
        self.stacked = _stack_optimizers(steppers, self.params)
        use_fused_adam([o.optimizer for o in self.stacked])  # as the compiled single-seed step
        super().__init__(
            {
                f"seed{seed}_{name}": loss
                for seed, s in zip(self.seeds, steppers, strict=True)
                for name, loss in s.losses.items()
            },
            [o.optimizer for o in self.stacked],
        )
        self.rng_states = [_copy_rng(s if isinstance(s, tuple) else (s, None)) for s in rng_states]
        self.device = next(iter(next(iter(self.params.values())).values())).device
        self._plain = detached(self.params)  # the update's arguments: views that follow the in-place updates
        self.compile, self.mode = bool(compile), mode
        self.compiled = False
        self._update = torch.vmap(update_gradients(names))
        self._fn = None
        # the fused kernel called straight, as the compiled step's
        self._adam = FusedAdamSteps(self.optimizers)

    def _seeds_values(self, name: str, key: str) -> torch.Tensor:
        """Parameter ``key`` of loss ``name`` of every seed's stepper, stacked along a leading seed dimension."""
        return torch.stack([s.losses[name].term_parameters()[key].detach() for s in self.steppers])

    def _build(self):
        fn = _with_own_code(self._update, f"vectorized_update_{len(self.seeds)}_seeds")
        return compile_update(fn, self.device, self.mode)

    def seed_inputs(self, batches: Sequence[TensorDictBase]) -> dict[str, dict[str, torch.Tensor]]:
        """Every seed's inputs (drawn from its own random stream), stacked along a leading seed dimension."""
        if len(batches) != len(self.seeds):
            raise ValueError(f"one batch per seed: {len(self.seeds)} seeds, {len(batches)} batches")
        outer = random_streams(self.device)
        per_seed = []
        try:
            for i, (stepper, batch) in enumerate(zip(self.steppers, batches, strict=True)):
                set_random_streams(self.device, self.rng_states[i])
                per_seed.append(step_inputs(stepper.losses, self.earlier[i], batch))
                self.rng_states[i] = random_streams(self.device)
        finally:
            set_random_streams(self.device, outer)
        return {
            name: {key: torch.stack([x[name][key] for x in per_seed]) for key in per_seed[0][name]}
            for name in self.steppers[0].losses
        }

    def batch(self, batches: Sequence[TensorDictBase]) -> TensorDict:
        """One batch per seed as one TensorDict (``seed<k>`` -> that seed's batch), what a Trainer hands on."""
        return TensorDict(
            {f"seed{seed}": b for seed, b in zip(self.seeds, batches, strict=True)}, batch_size=[]
        )

    def step(self, trainer, sub_batch: TensorDictBase | Sequence[TensorDictBase]) -> TensorDictBase:
        if isinstance(sub_batch, TensorDictBase):
            sub_batch = [sub_batch.get(f"seed{seed}") for seed in self.seeds]
        inputs = self.seed_inputs(sub_batch)
        args = (self._plain, inputs)
        if self.compile and self._fn is None:
            self._fn = self._build()
        if self._fn is not None:
            try:
                grads, (_, outputs) = self._fn(*args)
                self.compiled = True
            except Exception as err:
                if self.compiled:
                    raise
                warn_not_compiled("the vectorised update", err)
                self._fn, self.compile = None, False  # eager from now on
        if self._fn is None:
            grads, (_, outputs) = self._update(*args)
        self._apply_gradients(lambda: set_gradients(self.params, grads), replaces=True)
        set_gradients(self.params, None)
        return TensorDict(
            {
                f"{name}.{key}": value.detach().float()
                for name, out in outputs.items()
                for key, value in out.items()
                if value.shape == (len(self.seeds),)
            },
            batch_size=[],
        )

    def sync(self) -> None:
        """Write the stacked parameters and optimiser states back into every seed's stepper."""
        with torch.no_grad():
            for i, stepper in enumerate(self.steppers):
                for name, ps in step_parameters(stepper.losses).items():
                    for key, p in ps.items():
                        p.copy_(self.params[name][key][i])
        for o in self.stacked:
            o.write_to_seeds()

    def state_dict(self) -> dict[str, Any]:
        self.sync()
        return {
            "seeds": [s.state_dict() for s in self.steppers],
            "rng": [_copy_rng(r) for r in self.rng_states],
        }

    def load_state_dict(self, state_dict: Mapping[str, Any]) -> None:
        for stepper, state in zip(self.steppers, state_dict["seeds"], strict=True):
            stepper.load_state_dict(state)
        self.rng_states = [_copy_rng(r) for r in state_dict["rng"]]
        self.reload()

    def reload(self) -> None:
        """Stack the seeds' steppers again (after their parameters or optimiser states were loaded)."""
        with torch.no_grad():
            for name, ps in self.params.items():
                for key, p in ps.items():
                    p.copy_(self._seeds_values(name, key))
        for o in self.stacked:
            o.load_from_seeds()
        self._adam.reset()  # the stacked optimisers' state tensors are new ones

    def _step_optimizers(self) -> None:
        self._adam.step()


def _copy_rng(state: tuple) -> tuple:
    return tuple(_copy(s) for s in state)
