"""Offline training with :class:`torchrl.trainers.Trainer`: a batch source in place of the collector and one
optimisation step for several LossModules and optimisers.

TorchRL's :class:`~torchrl.trainers.Trainer` is built around a data collector: it iterates over the collector,
counts the collected frames, and runs ``optim_steps_per_batch`` optimisation steps per collected batch. Offline
there is nothing to collect, so :class:`OfflineBatchSource` yields empty TensorDicts whose batch size is the
number of optimisation steps they stand for: the Trainer's frame counter then counts optimisation steps, its
logging interval and hooks work unchanged (the progress bar is our labelled :class:`StepProgress`), and every
optimisation step draws its own batch from the replay buffers through a ``process_optim_batch`` hook
(:class:`SampleBuffers`). :class:`MultiLossStepper` (a TorchRL :class:`~torchrl.trainers.OptimizationStepper`)
evaluates several LossModules in order on that batch and steps all their optimisers; because each ``loss_*`` term
reaches only its own parameters (TorchRL's convention, tested for every loss of this package), one backward pass
through their sum equals one backward pass per optimiser.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.objectives import LossModule
from torchrl.trainers import OptimizationStepper, Trainer
from tqdm.auto import tqdm

from spoil_torchrl.divergence import check_finite
from spoil_torchrl.stopping import raise_if_stopped

#: What a diverged main stage is told to try.
DIVERGED_ADVICE = (
    "the run diverged: lower train.lr (and the algorithm's own rates) or check the data for extreme values"
)


class OfflineBatchSource:
    """Stands in for a TorchRL collector in :class:`~torchrl.trainers.Trainer` for offline training.

    Yields ``TensorDict(batch_size=[n])`` chunks with ``n = steps_per_batch`` (the last one smaller) until
    ``total_steps``: with ``frame_skip=1`` and ``optim_steps_per_batch=steps_per_batch`` the Trainer's
    "frames" are optimisation steps.

    Examples:
        >>> [chunk.batch_size[0] for chunk in OfflineBatchSource(total_steps=5, steps_per_batch=2)]
        [2, 2, 1]
    """

    init_random_frames = 0

    def __init__(self, total_steps: int, steps_per_batch: int) -> None:
        if total_steps < 1 or steps_per_batch < 1:
            raise ValueError(
                f"total_steps and steps_per_batch must be >= 1, got {total_steps} and {steps_per_batch}"
            )
        self.total_steps = int(total_steps)
        self.steps_per_batch = int(steps_per_batch)
        self.steps = 0

    def __iter__(self) -> Iterator[TensorDict]:
        while self.steps < self.total_steps:
            n = min(self.steps_per_batch, self.total_steps - self.steps)
            self.steps += n
            yield TensorDict(batch_size=[n])

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        return seed

    def shutdown(self) -> None:
        pass

    def update_policy_weights_(self, *args, **kwargs) -> None:
        pass

    def state_dict(self) -> dict[str, Any]:
        return {"steps": self.steps}

    def load_state_dict(self, state_dict: Mapping[str, Any]) -> None:
        self.steps = int(state_dict["steps"])


class SampleBuffers:
    """``process_optim_batch`` hook: replaces the placeholder chunk by a fresh replay-buffer sample per step.

    ``sample`` is e.g. :meth:`spoil_torchrl.data.DualDemoBuffers.sample` (one batch per role). The Trainer runs
    ``optim_steps_per_batch`` steps per chunk; after as many samples as the chunk stands for (fewer for a short
    last chunk) the hook raises ``StopIteration``, which ends the chunk's optimisation loop, so exactly
    ``total_steps`` steps run. :func:`offline_trainer` registers it as
    ``trainer.register_op("process_optim_batch", SampleBuffers(sample))``.

    Examples:
        >>> drawn = []
        >>> hook = SampleBuffers(lambda: TensorDict({"draw": torch.tensor([len(drawn)])}, [1]))
        >>> chunk = TensorDict(batch_size=[2])  # the placeholder of two optimisation steps
        >>> for _ in range(2):
        ...     drawn.append(hook(chunk)["draw"].item())
        >>> drawn
        [0, 1]
        >>> hook(chunk)  # the chunk's steps are done
        Traceback (most recent call last):
        ...
        StopIteration
        >>> hook(TensorDict(batch_size=[1]))["draw"].tolist()  # the next chunk starts afresh
        [2]
    """

    def __init__(self, sample: Callable[[], TensorDictBase]) -> None:
        self.sample = sample
        self._chunk: TensorDictBase | None = None
        self._done = 0

    def __call__(self, batch: TensorDictBase) -> TensorDictBase:
        if batch is not self._chunk:
            self._chunk, self._done = batch, 0
        if self._done >= batch.batch_size[0]:
            raise StopIteration
        self._done += 1
        return self.sample()


class StepEvery:
    """An optimiser that steps only on every ``interval``-th call of :meth:`step` (calls ``interval``,
    ``2 * interval``, ...), e.g. DWBC's discriminator, which its reference code updates once per 100 policy steps.

    It wraps the optimiser for :class:`MultiLossStepper`, which steps every optimiser each step; the gradient of
    the skipped steps is cleared by the next ``zero_grad``, as in the reference. The call count is part of the
    state dict.

    Examples:
        >>> p = torch.nn.Parameter(torch.zeros(()))
        >>> opt = StepEvery(torch.optim.SGD([p], lr=1.0), interval=3)
        >>> for _ in range(6):
        ...     opt.zero_grad()
        ...     (-p).backward()
        ...     opt.step()
        >>> p.item()  # stepped at calls 3 and 6
        2.0
    """

    def __init__(self, optimizer: torch.optim.Optimizer, interval: int) -> None:
        if int(interval) != interval or interval < 1:
            raise ValueError(f"interval must be a positive integer, got {interval}")
        self.optimizer = optimizer
        self.interval = int(interval)
        self.calls = 0

    @property
    def param_groups(self) -> list[dict[str, Any]]:
        return self.optimizer.param_groups

    def zero_grad(self, set_to_none: bool = True) -> None:
        self.optimizer.zero_grad(set_to_none=set_to_none)

    def step(self) -> None:
        self.calls += 1
        if self.calls % self.interval == 0:
            self.optimizer.step()

    def state_dict(self) -> dict[str, Any]:
        return {"optimizer": self.optimizer.state_dict(), "calls": self.calls}

    def load_state_dict(self, state_dict: Mapping[str, Any]) -> None:
        self.optimizer.load_state_dict(state_dict["optimizer"])
        self.calls = int(state_dict["calls"])


def scalar_outputs(outputs: Mapping[str, Mapping[str, torch.Tensor]]) -> TensorDict:
    """The scalar entries of each loss's outputs, detached, as ``<loss name>.<entry>`` (what a stepper returns).

    Examples:
        >>> scalar_outputs({"bc": {"loss_actor": torch.tensor(1.0), "per_sample": torch.ones(3)}})["bc.loss_actor"]
        tensor(1.)
    """
    return TensorDict(
        {
            f"{name}.{key}": value.detach()
            .float()
            .reshape(())  # the one value, without a kernel to average it
            for name, out in outputs.items()
            for key, value in out.items()
            if value.numel() == 1
        },
        batch_size=[],
    )


class MultiLossStepper(OptimizationStepper):
    """One optimisation step of several LossModules with their own optimisers (and LR schedules).

    The losses run in the given order on the same batch, so a loss may read what an earlier one wrote into it
    (:class:`~spoil_torchrl.objectives.SpoilDICELoss` writes the weights that
    :class:`~spoil_torchrl.objectives.WeightedBCLoss` reads). Returns the scalar entries of every loss output,
    detached, named ``<loss name>.<entry>``.

    Args:
        losses: name -> LossModule.
        optimizers: every optimiser over the losses' parameters (a :class:`StepEvery` steps less often).
        schedulers: LR schedulers stepped after the optimisers.

    Examples:
        One step by hand (:func:`offline_trainer` runs many, one per sampled batch):

        >>> from spoil_torchrl.modules import make_actor
        >>> from spoil_torchrl.objectives import WeightedBCLoss
        >>> safe = WeightedBCLoss(make_actor(3, 2, hidden_cells=(8,)), role="safe")
        >>> performant = WeightedBCLoss(make_actor(3, 2, hidden_cells=(8,)), role="performant")
        >>> optimizers = [torch.optim.Adam(loss.parameters(), lr=1e-3) for loss in (safe, performant)]
        >>> stepper = MultiLossStepper({"safe": safe, "perf": performant}, optimizers)
        >>> def role():  # a batch of 16 transitions
        ...     actions = torch.rand(16, 2) * 2 - 1
        ...     return TensorDict({"observation": torch.randn(16, 3), "action": actions}, [16])
        >>> out = stepper.step(None, TensorDict({"safe": role(), "performant": role()}, []))
        >>> sorted(key for key in out.keys() if "loss" in key)
        ['perf.loss_actor', 'safe.loss_actor']
        >>> [optimizer.state_dict()["state"][0]["step"].item() for optimizer in stepper.optimizers]
        [1.0, 1.0]
    """

    def __init__(
        self,
        losses: Mapping[str, LossModule],
        optimizers: Sequence[torch.optim.Optimizer],
        schedulers: Sequence[torch.optim.lr_scheduler.LRScheduler] = (),
    ) -> None:
        if not losses or not optimizers:
            raise ValueError("MultiLossStepper needs at least one loss and one optimizer")
        self.losses = dict(losses)
        self.optimizers = list(optimizers)
        self.schedulers = list(schedulers)

    def step(self, trainer: Trainer, sub_batch: TensorDictBase) -> TensorDictBase:
        outputs = {name: loss(sub_batch) for name, loss in self.losses.items()}
        total = sum(
            value for out in outputs.values() for key, value in out.items() if key.startswith("loss_")
        )
        self._apply_gradients(total.backward)
        return scalar_outputs(outputs)

    def _apply_gradients(self, set_gradients: Callable[[], None], *, replaces: bool = False) -> None:
        """Clear every optimiser's gradients, fill them with ``set_gradients`` (a backward pass, or gradients
        computed elsewhere), then step the optimisers and the schedules. ``replaces``: ``set_gradients`` gives
        every parameter it touches a new gradient (it assigns, it does not accumulate), so nothing is cleared."""
        if not replaces:
            for optimizer in self.optimizers:
                optimizer.zero_grad(set_to_none=True)
        set_gradients()
        self._step_optimizers()
        for scheduler in self.schedulers:
            scheduler.step()

    def _step_optimizers(self) -> None:
        """One step of every optimiser, in order."""
        for optimizer in self.optimizers:
            optimizer.step()

    def state_dict(self) -> dict[str, Any]:
        return {
            "losses": {name: loss.state_dict() for name, loss in self.losses.items()},
            "optimizers": [o.state_dict() for o in self.optimizers],
            "schedulers": [s.state_dict() for s in self.schedulers],
        }

    def load_state_dict(self, state_dict: Mapping[str, Any]) -> None:
        for name, loss in self.losses.items():
            loss.load_state_dict(state_dict["losses"][name])
        for o, s in zip(self.optimizers, state_dict["optimizers"], strict=True):
            o.load_state_dict(s)
        for o, s in zip(self.schedulers, state_dict["schedulers"], strict=True):
            o.load_state_dict(s)


class StepProgress:
    """A labelled progress bar over a Trainer's optimisation steps, with a short note (the last evaluation).

    Stands in for the Trainer's own bar, which has no label and whose description lists every value logged with
    ``log_pbar``. Updated at each chunk boundary (``post_steps``); a resumed Trainer starts it where it left off.

    Examples:
        >>> bar = StepProgress(1000, "training", enabled=False)
        >>> bar.update(300); bar.note("return 0.81, cost 0.40"); bar.close()
        >>> bar.steps, bar.text
        (300, 'return 0.81, cost 0.40')
    """

    def __init__(self, total: int, label: str, *, enabled: bool = True) -> None:
        self.total, self.label, self.enabled = int(total), label, enabled
        self.steps, self.text, self._bar = 0, "", None

    def update(self, steps: int) -> None:
        """Move the bar to ``steps`` optimisation steps done."""
        if self.enabled and self._bar is None:
            self._bar = tqdm(
                total=self.total, initial=steps, desc=self.label, unit="step", dynamic_ncols=True
            )
        elif self._bar is not None:
            self._bar.update(steps - self.steps)
        self.steps = steps

    def note(self, text: str) -> None:
        """Show ``text`` after the bar (kept short: one evaluation's two numbers)."""
        self.text = text
        if self._bar is not None:
            self._bar.set_postfix_str(text, refresh=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


class OfflineTrainer(Trainer):
    """TorchRL's :class:`~torchrl.trainers.Trainer` with a labelled :class:`StepProgress` bar (``progress``),
    closed when training ends or stops."""

    progress: StepProgress

    def train(self):
        self.progress.update(self.collected_frames)  # 0, or where a resumed Trainer left off
        try:
            return super().train()
        finally:
            self.progress.close()


def offline_trainer(
    stepper: MultiLossStepper,
    sample: Callable[[], TensorDictBase],
    *,
    total_steps: int,
    steps_per_batch: int = 100,
    logger=None,
    log_interval: int = 100,
    progress_bar: bool = True,
    progress_label: str = "training",
) -> OfflineTrainer:
    """A :class:`~torchrl.trainers.Trainer` that runs ``total_steps`` offline optimisation steps of ``stepper``,
    each on a fresh ``sample()``. Register further hooks (evaluation, checkpoints) with ``register_op``.
    ``progress_bar`` shows one bar labelled ``progress_label`` (``trainer.progress``; ``note`` adds a status).

    Examples:
        >>> from torch import nn
        >>> from spoil_torchrl.modules import make_actor
        >>> from spoil_torchrl.objectives import WeightedBCLoss
        >>> loss = WeightedBCLoss(make_actor(3, 2, hidden_cells=(8,)), role="performant")
        >>> stepper = MultiLossStepper({"bc": loss}, [torch.optim.Adam(loss.parameters(), lr=1e-3)])
        >>> drawn = []
        >>> def data():
        ...     drawn.append(1)
        ...     return TensorDict({"performant": TensorDict({"observation": torch.randn(16, 3),
        ...                                                  "action": torch.rand(16, 2) * 2 - 1}, [16])}, [])
        >>> trainer = offline_trainer(stepper, data, total_steps=25, steps_per_batch=10, progress_bar=False)
        >>> trainer.train()
        >>> trainer.collected_frames, len(drawn)  # one sample per optimisation step
        (25, 25)
    """
    trainer = OfflineTrainer(
        collector=OfflineBatchSource(total_steps, steps_per_batch),
        total_frames=total_steps,
        frame_skip=1,
        optim_steps_per_batch=steps_per_batch,
        loss_module=nn.ModuleDict(
            stepper.losses
        ),  # for Trainer.state_dict(); the stepper computes the losses
        optimization_stepper=stepper,
        logger=logger,
        log_interval=log_interval,
        progress_bar=False,  # our labelled bar instead (StepProgress)
        clip_grad_norm=False,
    )
    trainer.progress = StepProgress(total_steps, progress_label, enabled=progress_bar)
    trainer.register_op("post_steps", lambda: trainer.progress.update(trainer.collected_frames))
    trainer.register_op("process_optim_batch", SampleBuffers(sample))
    trainer.register_op("post_steps", raise_if_stopped)  # see spoil_torchrl.stopping.stop_on_signals

    def stop_if_diverged(optim_steps: int, losses: TensorDictBase | None) -> None:  # the chunk's mean losses
        for key, value in {} if losses is None else losses.items():
            check_finite(f"loss {key}", value, f"by step {trainer.collected_frames}", DIVERGED_ADVICE)

    trainer.register_op("post_optim_complete_log", stop_if_diverged)
    return trainer
