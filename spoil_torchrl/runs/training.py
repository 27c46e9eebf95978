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
from spoil_torchrl.objectives.keys import roles_read
from spoil_torchrl.runs.checkpoint import rng_state, set_rng_state
from spoil_torchrl.runs.seed_run import (
    Clock,
    PretrainedRun,
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


def use_penalty_form(stepper, train) -> None:
    """Give every DICE loss of ``stepper`` the gradient penalty's form ``train.penalty_form``
    (:attr:`~spoil_torchrl.objectives.dice.DICELoss.penalty_form`; absent: ``"autograd"``, the form of every
    committed result). Called before the first step, so a compiled step traces the form chosen."""
    form = train.get("penalty_form", "autograd")
    for loss in stepper.losses.values():
        if hasattr(loss, "penalty_form"):
            loss.penalty_form = form


def one_seed(run: PretrainedRun) -> Steps:
    """The steps of one seed's run: its own stepper (compiled with ``train.compile``; said and run eagerly
    where it cannot be), its buffers' batches."""
    stepper, buffers = (
        run.training.stepper,
        run.inputs.buffers,
    )  # as built (compiled: the same losses, optimisers)
    use_penalty_form(stepper, run.inputs.cfg.train)
    if run.inputs.cfg.train.compile:  # the whole update as one compiled graph
        stepper = CompiledStepper.from_stepper(stepper)

    def resume(trainer) -> None:
        state = run.inputs.checkpoint
        trainer.load_state_dict(state["trainer"])
        stepper.load_state_dict(state["stepper"])
        set_rng_state(state["rng"], buffers)

    roles = roles_read(stepper.losses.values(), buffers.roles)  # the others are not drawn

    return Steps(
        stepper,
        lambda: buffers.sample(roles),
        lambda trainer: [(trainer.state_dict(), rng_state(buffers))],
        resume,
        lambda: "compiled" if getattr(stepper, "compiled", False) else "eager",
    )


def vectorised_seeds(runs: list[PretrainedRun]) -> Steps:
    """The steps of several seeds at once: one vmapped update over their stacked networks
    (:class:`~spoil_torchrl.trainers.vectorized.VectorizedStepper`), each seed drawing from its own buffers and
    random stream, and each checkpointed as its single run would be."""
    for run in runs:
        use_penalty_form(run.training.stepper, run.inputs.cfg.train)
    stepper = VectorizedStepper(
        [r.training.stepper for r in runs],
        [r.random_state for r in runs],
        seeds=[int(r.inputs.cfg.seed) for r in runs],
        compile=bool(runs[0].inputs.cfg.train.compile),
    )

    def seed_states(trainer) -> list[tuple[dict, dict]]:
        whole = trainer.state_dict()  # (syncs every seed's stepper)
        states = []
        for i, run in enumerate(runs):
            own = run.training.stepper
            state = whole | {  # the trainer state of this seed's single-seed run
                "loss_module": nn.ModuleDict(own.losses).state_dict(),
                "optimization_stepper": own.state_dict(),
            }
            random = {"torch": stepper.rng_states[i][0], "buffers": run.inputs.buffers.rng_state()}
            states.append((state, random))
        return states

    def resume(trainer) -> None:
        states = [r.inputs.checkpoint for r in runs]
        seeds_state = {
            "seeds": [state["stepper"] for state in states],
            "rng": [(state["rng"]["torch"], None) for state in states],
        }
        trainer.load_state_dict(
            states[0]["trainer"]
            | {"loss_module": trainer.loss_module.state_dict(), "optimization_stepper": seeds_state}
        )
        for run, state in zip(runs, states, strict=True):
            run.inputs.buffers.set_rng_state(state["rng"]["buffers"])

    roles = roles_read(runs[0].training.stepper.losses.values(), runs[0].inputs.buffers.roles)

    return Steps(
        stepper,
        lambda: stepper.batch([run.inputs.buffers.sample(roles) for run in runs]),
        seed_states,
        resume,
        lambda: "vectorised, compiled" if stepper.compiled else "vectorised, eager",
    )


def train(runs: list[PretrainedRun], *, vectorised: bool | None = None) -> list[dict]:
    """The main stage of every seed in ``runs``: one Trainer, each seed evaluated, logged and checkpointed as
    its own run. ``vectorised`` (default: more than one seed) trains them in one vmapped update
    (:func:`vectorised_seeds`), else the one seed with its own stepper (:func:`one_seed`). Returns each seed's
    finished ``results.json`` content."""
    cfg = runs[0].inputs.cfg
    for run in runs:
        run.inputs.results["status"] = "training"
    clocks = [main_stage_clock(run.inputs) for run in runs]
    vectorised = len(runs) > 1 if vectorised is None else vectorised
    steps = vectorised_seeds(runs) if vectorised else one_seed(runs[0])
    several = f", {len(runs)} seeds" if len(runs) > 1 else ""
    trainer = offline_trainer(
        steps.stepper,
        steps.sample,
        total_steps=int(cfg.train.steps),
        steps_per_batch=_steps_per_batch(cfg.train),
        progress_bar=cfg.progress,
        progress_label=f"training {cfg.algo.name}{several}",
    )
    if runs[0].inputs.checkpoint is not None:  # continue exactly where the checkpoints were taken
        steps.resume(trainer)
    with contextlib.ExitStack() as stack:
        for run in runs:  # every evaluation episode into the seed's MCAP file, flushed per episode
            run.inputs.evaluator.writer = stack.enter_context(rollout_writer(run.inputs))
        # the seeds' rollouts on the spare cores too (a CUDA policy stays in this process: forked workers
        # cannot take it)
        on_cpu = runs[0].inputs.buffers.device.type == "cpu"
        workers = min(len(runs), available_cores()) - 1 if on_cpu else 0
        pool = stack.enter_context(RolloutPool(workers=workers, warm_up=ROLLOUT_MODULES))
        _register_hooks(trainer, runs, steps, clocks, pool)
        trainer.train()
    if hasattr(steps.stepper, "sync"):
        steps.stepper.sync()
    return [finish(run, steps.label(), clock) for run, clock in zip(runs, clocks, strict=True)]


def _register_hooks(trainer, runs: list[PretrainedRun], steps: Steps, clocks: list[Clock], pool) -> None:
    """The main stage's hooks, the same for one seed and several: each seed's losses logged every
    ``train.log_interval`` steps, and every ``train.eval_interval`` steps each seed evaluated (its rollouts on
    ``pool``'s spare cores too), logged and checkpointed."""
    train_cfg = runs[0].inputs.cfg.train
    last_count = [0]  # the step of the last optim_steps row

    def log_losses(optim_steps: int, losses) -> None:  # each seed's averages into its own logger
        step, interval = trainer.collected_frames, int(train_cfg.log_interval)
        if losses is not None and step // interval != (step - trainer.optim_steps_per_batch) // interval:
            _log_per_seed(runs, losses, step)
        if step - last_count[0] > interval:  # the step count, at the TorchRL Trainer's own cadence
            last_count[0] = step
            _log_per_seed(runs, {"optim_steps": [float(optim_steps)] * len(runs)}, step)

    def evaluate_now(batch) -> None:
        step = trainer.collected_frames
        if evaluation_due(step, runs[0].inputs.cfg):
            _evaluate_seeds(trainer, runs, steps, clocks, pool, step)

    trainer.register_op("post_optim_complete_log", log_losses)
    trainer.register_op("post_steps_log", evaluate_now)


def _evaluate_seeds(trainer, runs: list[PretrainedRun], steps: Steps, clocks: list[Clock], pool, step: int):
    """Evaluate, log and checkpoint every seed after ``step`` steps; say the seeds' mean on the progress bar."""
    if hasattr(steps.stepper, "sync"):  # every seed's stepper holds its networks, optimiser states again
        steps.stepper.sync()
    results, started = [], time.perf_counter()
    rollouts = pool.map([rollout_job(run) for run in runs])  # on the spare cores too
    for run, clock in zip(runs, clocks, strict=True):  # a seed's time: from the previous seed's end
        results.append(evaluate(run, step, clock, next(rollouts), started))
        started = time.perf_counter()
    _log_per_seed(runs, {f"eval/{key}": [r[key] for r in results] for key in METRICS}, step)
    if runs[
        0
    ].inputs.cfg.train.checkpoint:  # a kill while they are written leaves each seed one of the step before
        if len(runs) > 1:
            keep_previous_checkpoints([run.inputs.run_dir for run in runs])
        for run, clock, (state, random) in zip(runs, clocks, steps.seed_states(trainer), strict=True):
            save_state(run, step, state, random, clock)
    mean = {key: sum(r[key] for r in results) / len(results) for key in METRICS}
    of = f" (mean of {len(runs)} seeds)" if len(runs) > 1 else ""
    trainer.progress.note(
        f"step {step}: feasible return {mean['normalized_feasible_return']:.2f}, "
        f"cost {mean['normalized_cost']:.2f}{of}"
    )


def _log_per_seed(runs: list[PretrainedRun], values, step: int) -> None:
    """Log ``values`` (key -> one value per seed: a list, or a tensor of shape ``[seeds]`` or ``[]``) into
    each seed's own logger at ``step``."""
    for i, run in enumerate(runs):
        logger = run.inputs.logger
        if logger is not None:
            for key, value in values.items():
                one = value[i] if isinstance(value, list) else value.reshape(-1)[i]
                logger.log_scalar(key, float(one), step=step)


def train_one(run: PretrainedRun) -> dict:
    """:func:`train` for one seed's run; returns its finished ``results.json`` content."""
    return train([run])[0]
