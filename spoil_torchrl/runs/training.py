"""The main stage of a run (Algorithm 1's loop): optimise the algorithm's losses with the TorchRL Trainer,
evaluating every ``train.eval_interval`` steps, checkpointing after each evaluation, and finishing with the
paper's aggregate.

:func:`train` is the one loop, for one seed and for the seeds of a ``seeds=[...]`` run. What differs is the
stepper (:class:`Steps`): one seed's own (compiled with ``train.compile``), or every seed's networks stacked
along a seed dimension in one vmapped, compiled update
(:class:`~spoil_torchrl.trainers.vectorized.VectorizedStepper`). The hooks are written once: each seed's
losses logged into its own logger, each seed evaluated (the rollouts of several seeds on the spare cores too),
logged and checkpointed as its own run, and finished with its aggregate.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

from torch import nn

from spoil_torchrl.data.collect import ROLLOUT_MODULES
from spoil_torchrl.data.parallel import RolloutPool, available_cores
from spoil_torchrl.eval.evaluator import METRICS
from spoil_torchrl.runs.checkpoint import rng_state, set_rng_state
from spoil_torchrl.runs.seed_run import (
    SeedRun,
    evaluate,
    evaluation_due,
    finish,
    keep_previous_checkpoints,
    main_stage_clock,
    rollout_job,
    rollout_writer,
    save_state,
)
from spoil_torchrl.trainers import CompiledStepper, offline_trainer
from spoil_torchrl.trainers.vectorized import VectorizedStepper


def _steps_per_batch(train) -> int:
    """Steps between the Trainer's hooks: a divisor of the evaluation interval and of the budget, at most 100."""
    return math.gcd(int(train.eval_interval), int(train.steps), 100)


@dataclass
class Steps:
    """What the main stage steps and draws, for one seed or several.

    Attributes:
        stepper: the Trainer's optimisation stepper.
        sample: one batch for it (every seed's batch, for several).
        seed_states: ``trainer -> [(trainer state, random state)]``, one per seed, as that seed's single run
            checkpoints it (called after an evaluation).
        resume: ``trainer -> None``: the stepper, the Trainer's counters and every random stream put back where
            the seeds' checkpoints were taken.
        label: how the update ran, for ``results.json`` (``update_step``), once training has run.
    """

    stepper: object
    sample: Callable
    seed_states: Callable
    resume: Callable
    label: Callable[[], str]


def one_seed(seed_run: SeedRun) -> Steps:
    """The steps of one seed's run: its own stepper (compiled with ``train.compile``; said and run eagerly
    where it cannot be), its buffers' batches."""
    stepper = seed_run.training.stepper  # as built (compiled: the same losses and optimisers)
    if seed_run.cfg.train.compile:  # the whole update as one compiled graph
        stepper = CompiledStepper.from_stepper(stepper)

    def resume(trainer) -> None:
        state = seed_run.state
        trainer.load_state_dict(state["trainer"])
        stepper.load_state_dict(state["stepper"])
        set_rng_state(state["rng"], seed_run.buffers)

    return Steps(
        stepper,
        seed_run.buffers.sample,
        lambda trainer: [(trainer.state_dict(), rng_state(seed_run.buffers))],
        resume,
        lambda: "compiled" if getattr(stepper, "compiled", False) else "eager",
    )


def vectorised_seeds(runs: list[SeedRun]) -> Steps:
    """The steps of several seeds at once: one vmapped update over their stacked networks
    (:class:`~spoil_torchrl.trainers.vectorized.VectorizedStepper`), each seed drawing from its own buffers and
    random stream, and each checkpointed as its single run would be."""
    stepper = VectorizedStepper(
        [r.training.stepper for r in runs],
        [r.random_state for r in runs],
        seeds=[int(r.cfg.seed) for r in runs],
        compile=bool(runs[0].cfg.train.compile),
    )

    def seed_states(trainer) -> list[tuple[dict, dict]]:
        whole = trainer.state_dict()  # (syncs every seed's stepper)
        states = []
        for i, seed_run in enumerate(runs):
            own = seed_run.training.stepper
            state = whole | {  # the trainer state of this seed's single-seed run
                "loss_module": nn.ModuleDict(own.losses).state_dict(),
                "optimization_stepper": own.state_dict(),
            }
            random = {"torch": stepper.rng_states[i][0], "buffers": seed_run.buffers.rng_state()}
            states.append((state, random))
        return states

    def resume(trainer) -> None:
        seeds_state = {
            "seeds": [r.state["stepper"] for r in runs],
            "rng": [(r.state["rng"]["torch"], None) for r in runs],
        }
        trainer.load_state_dict(
            runs[0].state["trainer"]
            | {"loss_module": trainer.loss_module.state_dict(), "optimization_stepper": seeds_state}
        )
        for seed_run in runs:
            seed_run.buffers.set_rng_state(seed_run.state["rng"]["buffers"])

    return Steps(
        stepper,
        lambda: stepper.batch([seed_run.buffers.sample() for seed_run in runs]),
        seed_states,
        resume,
        lambda: "vectorised, compiled" if stepper.compiled else "vectorised, eager",
    )


def train(runs: list[SeedRun], *, vectorised: bool | None = None) -> list[dict]:
    """The main stage of every seed in ``runs``: one Trainer, each seed evaluated, logged and checkpointed as
    its own run. ``vectorised`` (default: more than one seed) trains them in one vmapped update
    (:func:`vectorised_seeds`), else the one seed with its own stepper (:func:`one_seed`). Returns each seed's
    finished ``results.json`` content."""
    cfg, train_cfg = runs[0].cfg, runs[0].cfg.train
    for seed_run in runs:
        seed_run.results["status"] = "training"
    starts = [main_stage_clock(seed_run) for seed_run in runs]
    vectorised = len(runs) > 1 if vectorised is None else vectorised
    steps = vectorised_seeds(runs) if vectorised else one_seed(runs[0])
    several = f", {len(runs)} seeds" if len(runs) > 1 else ""
    trainer = offline_trainer(
        steps.stepper,
        steps.sample,
        total_steps=int(train_cfg.steps),
        steps_per_batch=_steps_per_batch(train_cfg),
        progress_bar=cfg.progress,
        progress_label=f"training {cfg.algo.name}{several}",
    )

    def log_losses(optim_steps: int, losses) -> None:  # each seed's averages into its own logger
        step, interval = trainer.collected_frames, int(train_cfg.log_interval)
        if losses is not None and step // interval != (step - trainer.optim_steps_per_batch) // interval:
            _log_per_seed(runs, losses, step)

    def evaluate_now(batch) -> None:
        step = trainer.collected_frames
        if not evaluation_due(step, cfg):
            return
        if hasattr(steps.stepper, "sync"):  # every seed's stepper holds its networks, optimiser states again
            steps.stepper.sync()
        results, started = [], time.perf_counter()
        rollouts = pool.map([rollout_job(seed_run) for seed_run in runs])  # on the spare cores too
        for seed_run, t0 in zip(runs, starts, strict=True):  # a seed's time: from the previous seed's end
            results.append(evaluate(seed_run, step, t0, next(rollouts), started))
            started = time.perf_counter()
        _log_per_seed(runs, {f"eval/{key}": [r[key] for r in results] for key in METRICS}, step)
        if train_cfg.checkpoint:  # a kill while they are written leaves each seed one of the step before
            if len(runs) > 1:
                keep_previous_checkpoints([seed_run.run_dir for seed_run in runs])
            for seed_run, t0, (state, random) in zip(runs, starts, steps.seed_states(trainer), strict=True):
                save_state(seed_run, step, state, random, t0)
        mean = {key: sum(r[key] for r in results) / len(results) for key in METRICS}
        of = f" (mean of {len(runs)} seeds)" if len(runs) > 1 else ""
        trainer.progress.note(
            f"step {step}: feasible return {mean['normalized_feasible_return']:.2f}, "
            f"cost {mean['normalized_cost']:.2f}{of}"
        )

    trainer.register_op("post_optim_complete_log", log_losses)
    trainer.register_op("post_steps_log", evaluate_now)
    if runs[0].state is not None:  # continue exactly where the checkpoints were taken
        steps.resume(trainer)
    with contextlib.ExitStack() as stack:
        for seed_run in runs:  # every evaluation episode into the seed's MCAP file, flushed per episode
            seed_run.evaluator.writer = stack.enter_context(rollout_writer(seed_run))
        pool = stack.enter_context(
            RolloutPool(workers=min(len(runs), available_cores()) - 1, warm_up=ROLLOUT_MODULES)
        )
        trainer.train()
    if hasattr(steps.stepper, "sync"):
        steps.stepper.sync()
    return [finish(seed_run, steps.label(), t0) for seed_run, t0 in zip(runs, starts, strict=True)]


def _log_per_seed(runs: list[SeedRun], values, step: int) -> None:
    """Log ``values`` (key -> one value per seed: a list, or a tensor of shape ``[seeds]`` or ``[]``) into
    each seed's own logger at ``step``."""
    for i, seed_run in enumerate(runs):
        if seed_run.logger is not None:
            for key, value in values.items():
                one = value[i] if isinstance(value, list) else value.reshape(-1)[i]
                seed_run.logger.log_scalar(key, float(one), step=step)


def train_one(seed_run: SeedRun) -> dict:
    """:func:`train` for one seed's run; returns its finished ``results.json`` content."""
    return train([seed_run])[0]
