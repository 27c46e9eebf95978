"""The main stage of a run (Algorithm 1's loop): optimise the algorithm's losses with the TorchRL Trainer,
evaluating every ``train.eval_interval`` steps, checkpointing after each evaluation, and finishing with the
paper's aggregate. :func:`train_one` trains one seed; :func:`train_seeds` trains the seeds of a ``seeds=[...]``
run at once (the networks stacked along a seed dimension, one vmapped, compiled update,
:class:`~spoil_torchrl.trainers.vectorized.VectorizedStepper`), each seed evaluated, logged and checkpointed as
its own run."""

from __future__ import annotations

import contextlib
import math
import time

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


def train_one(seed_run: SeedRun) -> dict:
    """Optimise the main stage with the TorchRL Trainer, evaluating every ``train.eval_interval`` steps; returns
    the content of the finished ``results.json``."""
    cfg, training, train = seed_run.cfg, seed_run.training, seed_run.cfg.train
    seed_run.results["status"] = "training"
    train_start = main_stage_clock(seed_run)

    def evaluate_now(batch) -> dict | None:
        step = trainer.collected_frames
        if not evaluation_due(step, cfg):
            return None
        result = evaluate(seed_run, step, train_start)
        trainer.progress.note(
            f"step {step}: feasible return {result['normalized_feasible_return']:.2f}, "
            f"cost {result['normalized_cost']:.2f}"
        )
        return {f"eval/{key}": result[key] for key in METRICS}

    def checkpoint(batch) -> None:  # runs after the Trainer has logged the evaluation
        step, evaluations = trainer.collected_frames, seed_run.results["evaluations"]
        if train.checkpoint and evaluations and evaluations[-1]["step"] == step:
            save_state(seed_run, step, trainer.state_dict(), rng_state(seed_run.buffers), train_start)

    if train.compile:  # the whole update as one compiled graph; says so and runs eagerly where it cannot
        training.stepper = CompiledStepper.from_stepper(training.stepper)
    trainer = offline_trainer(
        training.stepper,
        seed_run.buffers.sample,
        total_steps=int(train.steps),
        steps_per_batch=_steps_per_batch(train),
        logger=seed_run.logger,
        log_interval=int(train.log_interval),
        progress_bar=cfg.progress,
        progress_label=f"training {cfg.algo.name}",
    )
    trainer.register_op("post_steps_log", evaluate_now)
    trainer.register_op("post_steps_log", checkpoint)
    state = seed_run.state
    if state is not None:  # continue exactly where the checkpoint was taken
        trainer.load_state_dict(state["trainer"])
        training.stepper.load_state_dict(state["stepper"])
        set_rng_state(state["rng"], seed_run.buffers)
    with rollout_writer(
        seed_run
    ) as writer:  # every evaluation episode into the MCAP file, flushed per episode
        seed_run.evaluator.writer = writer
        trainer.train()
    return finish(
        seed_run, "compiled" if getattr(training.stepper, "compiled", False) else "eager", train_start
    )


def train_seeds(runs: list[SeedRun]) -> list[dict]:
    """The main stage of every seed at once: one Trainer, one vmapped update; each seed evaluated, logged and
    checkpointed as its own run. Returns each seed's finished ``results.json`` content."""
    cfg, train = runs[0].cfg, runs[0].cfg.train
    for seed_run in runs:
        seed_run.results["status"] = "training"
    starts = [main_stage_clock(seed_run) for seed_run in runs]
    stepper = VectorizedStepper(
        [r.training.stepper for r in runs],
        [r.random_state for r in runs],
        seeds=[int(r.cfg.seed) for r in runs],
        compile=bool(train.compile),
    )
    trainer = offline_trainer(
        stepper,
        lambda: stepper.batch([seed_run.buffers.sample() for seed_run in runs]),
        total_steps=int(train.steps),
        steps_per_batch=_steps_per_batch(train),
        progress_bar=cfg.progress,
        progress_label=f"training {cfg.algo.name}, {len(runs)} seeds",
    )

    def log_losses(optim_steps: int, losses) -> None:  # each seed's averages into its own logger
        step, interval = trainer.collected_frames, int(train.log_interval)
        if losses is None or step // interval == (step - trainer.optim_steps_per_batch) // interval:
            return
        for i, seed_run in enumerate(runs):
            if seed_run.logger is not None:
                for key, value in losses.items():
                    seed_run.logger.log_scalar(key, float(value[i]), step=step)

    def evaluate_now(batch) -> None:
        step = trainer.collected_frames
        if not evaluation_due(step, cfg):
            return
        stepper.sync()  # every seed's stepper holds its networks and optimiser states again
        rollouts = pool.map([rollout_job(seed_run) for seed_run in runs])  # on the spare cores too
        results, started = [], time.perf_counter()
        for seed_run, t0 in zip(runs, starts, strict=True):  # a seed's time: from the previous seed's end
            results.append(evaluate(seed_run, step, t0, next(rollouts), started))
            started = time.perf_counter()
        for seed_run, result in zip(runs, results, strict=True):
            if seed_run.logger is not None:
                for key in METRICS:
                    seed_run.logger.log_scalar(f"eval/{key}", result[key], step=step)
        if train.checkpoint:  # a kill while they are written leaves each seed one of the step before
            keep_previous_checkpoints([seed_run.run_dir for seed_run in runs])
            whole = trainer.state_dict()
            for i, (seed_run, t0) in enumerate(zip(runs, starts, strict=True)):
                own = seed_run.training.stepper
                state = whole | {  # the trainer state of this seed's single-seed run
                    "loss_module": nn.ModuleDict(own.losses).state_dict(),
                    "optimization_stepper": own.state_dict(),
                }
                random = {"torch": stepper.rng_states[i][0], "buffers": seed_run.buffers.rng_state()}
                save_state(seed_run, step, state, random, t0)
        mean = {key: sum(r[key] for r in results) / len(results) for key in METRICS}
        trainer.progress.note(
            f"step {step}: feasible return {mean['normalized_feasible_return']:.2f}, "
            f"cost {mean['normalized_cost']:.2f} (mean of {len(runs)} seeds)"
        )

    trainer.register_op("post_optim_complete_log", log_losses)
    trainer.register_op("post_steps_log", evaluate_now)
    if runs[0].state is not None:  # every seed, and the Trainer's counters, where the checkpoints were taken
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
    with contextlib.ExitStack() as stack:
        for seed_run in runs:
            seed_run.evaluator.writer = stack.enter_context(rollout_writer(seed_run))
        pool = stack.enter_context(
            RolloutPool(workers=min(len(runs), available_cores()) - 1, warm_up=ROLLOUT_MODULES)
        )
        trainer.train()
    stepper.sync()
    update_step = "vectorised, compiled" if stepper.compiled else "vectorised, eager"
    return [finish(seed_run, update_step, t0) for seed_run, t0 in zip(runs, starts, strict=True)]
