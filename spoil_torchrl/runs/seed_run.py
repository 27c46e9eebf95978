"""One seed's run of the main recipe as the values its stages return, and the bookkeeping every run does the
same way, alone or as one of the seeds of a ``seeds=[...]`` run.

A run's stages hand each other immutable values: :func:`~spoil_torchrl.runs.lifecycle.open_run` returns
:class:`RunInputs` (settings, directory, data, evaluator, logger, the checkpoint it continues from),
:func:`~spoil_torchrl.runs.lifecycle.pretrain` returns a :class:`PretrainedRun` (those inputs plus the
algorithm's pre-training and the main stage built on it), and the main stage
(:func:`~spoil_torchrl.runs.training.train`) reads one of those and returns ``results.json``'s content. No
stage changes another's value; the one record every stage adds to is ``results`` (``results.json``'s content,
rewritten as the run goes). The functions here evaluate the policy and rewrite ``results.json``
(:func:`evaluate`), checkpoint (:func:`save_state`), write the MCAP file (:func:`rollout_writer`), record why a
run stopped (:func:`recorded_failure`) and finish with the paper's aggregate (:func:`finish`).
"""

from __future__ import annotations

import contextlib
import copy
import logging
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import DictConfig

from spoil_torchrl.algorithms import PolicyTraining, Pretraining
from spoil_torchrl.data import DualDemoBuffers
from spoil_torchrl.data.parallel import Job
from spoil_torchrl.divergence import check_finite
from spoil_torchrl.eval import Evaluator, RolloutWriter
from spoil_torchrl.eval.dice_diagnostics import annotated_support_accuracy, dice_diagnostics, summary_scalars
from spoil_torchrl.eval.dice_explain import explain
from spoil_torchrl.eval.mcap_resume import continue_rollouts
from spoil_torchrl.precision import matmul_check
from spoil_torchrl.runs.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from spoil_torchrl.runs.directory import CHECKPOINT_NAME, write_lock
from spoil_torchrl.runs.results import aggregate, write_json
from spoil_torchrl.runs.resume import csv_row_counts
from spoil_torchrl.trainers.offline import DIVERGED_ADVICE
from spoil_torchrl.zoo import save_policy

log = logging.getLogger(__name__)

#: A seed's checkpoint before the last one, kept by a ``seeds=[...]`` run (relative to the seed's directory).
PREVIOUS_CHECKPOINT = "checkpoints/training_state.previous.pt"


@dataclass(frozen=True)
class RunInputs:
    """One seed's run as :func:`~spoil_torchrl.runs.lifecycle.open_run` loads it: the input of Algorithm 1.

    Attributes:
        cfg: the seed's settings.
        run_dir: its run directory.
        results: ``results.json``'s content, the run's record (each stage adds its part and rewrites the file).
        buffers: D_S, D_P, D_U and D_0 (and any extra role), states standardised. The pre-training adds its
            annotation columns to them (Algorithm 1 annotates D_U once); it changes no column they had.
        evaluator: rolls the policy out in the task.
        logger: the TorchRL logger (``None``: none).
        norm: the observation statistics (``None``: not standardised).
        metadata: the dataset's metadata.
        checkpoint: the checkpoint's content the run continues from (``None``: it starts).
        start: when the run started (``time.perf_counter``).
        random_state: torch's random state once the run is open (where its pre-training starts drawing).
        stored: the pre-training the run stored, loaded on resume and written back into ``buffers``
            (``None``: computed by :func:`~spoil_torchrl.runs.lifecycle.pretrain`).
    """

    cfg: DictConfig
    run_dir: Path
    results: dict
    buffers: DualDemoBuffers
    evaluator: Evaluator
    logger: object
    norm: object
    metadata: Mapping
    checkpoint: dict | None
    start: float
    random_state: torch.Tensor
    stored: Pretraining | None = None


@dataclass(frozen=True)
class DiceProbe:
    """The fixed inputs of the DICE diagnostics (never read by training): the segments' pools, D_P's support
    estimate against the true cost, and a fixed subsample of the DICE role plus D_0 on which (nu, lambda) are
    examined at every evaluation."""

    pools: Mapping | None
    support: dict | None
    transitions: object
    initial: object


@dataclass(frozen=True)
class PretrainedRun:
    """One seed's run once :func:`~spoil_torchrl.runs.lifecycle.pretrain` has run: its inputs, the algorithm's
    pre-training (computed, or the stored one), the main stage built on it, the pre-training's fingerprint
    (checkpointed, for runs from before pre-trainings were stored), the DICE diagnostics' probe (``None`` for
    methods without a DICE dual) and torch's random state where the main stage starts drawing."""

    inputs: RunInputs
    pretraining: Pretraining
    training: PolicyTraining
    fingerprint: str
    probe: DiceProbe | None
    random_state: torch.Tensor


@dataclass(frozen=True)
class Clock:
    """The main stage's clocks (``time.perf_counter``), a resumed run's shifted by the time before its
    checkpoint: ``run`` counts ``total_seconds``, ``train`` counts ``train_seconds``."""

    run: float
    train: float


def main_stage_clock(inputs: RunInputs) -> Clock:
    """The main stage's clocks, started now (a resumed run counts the time before its checkpoint)."""
    state, now = inputs.checkpoint, time.perf_counter()
    if state is None:
        return Clock(inputs.start, now)
    return Clock(inputs.start - state["total_seconds"], now - state["train_seconds"])


@contextlib.contextmanager
def recorded_failure(runs: list[RunInputs]):
    """Keep what was done: on any error or interruption every run's ``results.json`` says why it stopped."""
    try:
        yield
    except BaseException as err:
        for inputs in runs:
            inputs.results["status"] = "interrupted" if isinstance(err, KeyboardInterrupt) else "failed"
            inputs.results["error"] = f"{type(err).__name__}: {err}"
            write_json(inputs.run_dir / "results.json", inputs.results)
        raise


def note_precision(runs: list[RunInputs]) -> None:
    """Record the matmul precision training runs at, and its measured error, in every run's results."""
    error = matmul_check(runs[0].buffers.device)  # as the training device computes them
    for inputs in runs:
        inputs.results["matmul_precision"] = torch.get_float32_matmul_precision()
        inputs.results["matmul_relative_error"] = error


def performant_support(buffers, pools) -> dict | None:
    """The support estimate on D_P against the true cost (``None`` where the algorithm annotated none)."""
    if "performant" not in buffers.roles:
        return None
    performant = buffers["performant"].storage[:]
    if "safe_support" not in performant.keys():
        return None
    return annotated_support_accuracy(performant, pools)


def rollout_job(run: PretrainedRun) -> Job:
    """The evaluation rollout of the seed's current policy (a copy) as a job for a
    :class:`~spoil_torchrl.data.parallel.RolloutPool`."""
    with run.training.policy() as policy:
        return run.inputs.evaluator.rollout_job(copy.deepcopy(policy))


def evaluate(
    run: PretrainedRun,
    step: int,
    clock: Clock,
    rollout: dict | None = None,
    started: float | None = None,
) -> dict:
    """Evaluate the seed's current policy in the task (episodes into its MCAP file), save its policy file and
    the DICE diagnostics, and rewrite ``results.json``; returns the evaluation.

    ``rollout``: the evaluation's episodes, when they were rolled out elsewhere (:func:`rollout_job`), else they
    are rolled out here. ``started``: when the evaluation's time (``eval_seconds``) started, if before the call
    (a ``seeds=[...]`` run counts from the previous seed's end: the rollouts its main process ran fall to the
    first seed, and the seeds' times add up to the round's).
    """
    inputs, training = run.inputs, run.training
    evaluation_start = time.perf_counter() if started is None else started
    with training.policy() as policy:
        for name, weight in policy.named_parameters():  # a diverged policy is never evaluated
            check_finite(f"policy weight {name}", weight.detach(), f"step {step}", DIVERGED_ADVICE)
        evaluator = inputs.evaluator
        result = evaluator(policy, step) if rollout is None else evaluator.report(rollout, step)
        if inputs.cfg.train.checkpoint:
            _save_policy_file(inputs, policy, step)
    if run.probe is not None:
        result["dice"] = _dice_diagnostics(run, step)
    result["seconds"] = time.perf_counter() - clock.train
    result["eval_seconds"] = time.perf_counter() - evaluation_start  # rollouts, policy file, diagnostics
    inputs.results["evaluations"].append(result)
    write_json(inputs.run_dir / "results.json", inputs.results)
    return result


def _save_policy_file(inputs: RunInputs, policy, step: int) -> None:
    """The evaluated policy as the run's policy file (``checkpoints/policy.pt``)."""
    cfg = inputs.cfg
    save_policy(
        inputs.run_dir / "checkpoints" / "policy.pt",
        policy,
        env_id=cfg.task.env_id,
        distribution=cfg.algo.distribution,
        info={"step": step, "algo": cfg.algo.name, "config_hash": inputs.results["config_hash"]},
    )


def _dice_diagnostics(run: PretrainedRun, step: int) -> dict:
    """The DICE diagnostics of (nu, lambda) on the run's probe, into ``results`` and the logger; returns their
    summary scalars."""
    probe, training, inputs = run.probe, run.training, run.inputs
    dice = dice_diagnostics(
        training.dice, probe.transitions, probe.initial, role=training.dice_role, pools=probe.pools
    )
    inputs.results.update(dice_diagnostics=dice, dice_report=explain(dice, probe.support))
    scalars = summary_scalars(dice)
    if inputs.logger is not None:
        for key, value in scalars.items():
            inputs.logger.log_scalar(key, value, step=step)
    return scalars


def save_state(run: PretrainedRun, step: int, trainer_state: dict, random_state: dict, clock: Clock) -> None:
    """After an evaluation and its log rows: everything the seed's run needs to continue from here."""
    inputs = run.inputs
    save_checkpoint(
        inputs.run_dir / CHECKPOINT_NAME,
        {
            "step": step,
            "config_yaml": (inputs.run_dir / "config.yaml").read_text(),
            "trainer": trainer_state,
            "stepper": trainer_state["optimization_stepper"],
            "rng": random_state,
            "results": inputs.results,
            "pretraining": run.fingerprint,
            "csv_rows": csv_row_counts(inputs.run_dir / "logs"),
            "train_seconds": time.perf_counter() - clock.train,
            "total_seconds": time.perf_counter() - clock.run,
        },
    )
    write_lock(inputs.run_dir)  # heartbeat


def finish(run: PretrainedRun, update_step: str, clock: Clock) -> dict:
    """Output: ``results.json`` with the paper's aggregate of the last evaluations."""
    inputs = run.inputs
    results = inputs.results
    last = min(int(inputs.cfg.train.last_evaluations), len(results["evaluations"]))
    results.update(
        status="finished",
        aggregate=aggregate(results["evaluations"], last),
        last_evaluations=last,
        update_step=update_step,
        train_seconds=time.perf_counter() - clock.train,
        total_seconds=time.perf_counter() - clock.run,
    )
    write_json(inputs.run_dir / "results.json", results)
    return results


def rollout_writer(inputs: RunInputs):
    """The seed's MCAP writer: a new file, or the run's file continued after the checkpoint's step."""
    cfg, results = inputs.cfg, inputs.results
    metadata = {
        "task": cfg.task.env_id,
        "algo": cfg.algo.name,
        "seed": cfg.seed,
        "config_hash": results["config_hash"],
    }
    mcap = dict(
        path=inputs.run_dir / "rollouts.mcap",
        cost_threshold=inputs.evaluator.cost_threshold,
        metadata=metadata,
    )
    if inputs.checkpoint is None:
        return RolloutWriter(**mcap)
    return continue_rollouts(**mcap, until_step=inputs.checkpoint["step"])


def evaluation_due(step: int, cfg: DictConfig) -> bool:
    """Whether the main stage evaluates after ``step`` steps: every ``train.eval_interval`` and at the end."""
    return step % int(cfg.train.eval_interval) == 0 or step >= int(cfg.train.steps)


def keep_previous_checkpoints(run_dirs: list[Path]) -> None:
    """Before a ``seeds=[...]`` run writes its seeds' checkpoints: each seed's current one becomes its previous
    one (a hard link, replaced atomically). A run killed while writing them leaves every seed a checkpoint of the
    step before, from which :func:`common_checkpoints` continues them all."""
    for run_dir in run_dirs:
        current = run_dir / CHECKPOINT_NAME
        if current.is_file():
            link = current.with_name(current.name + ".link")
            link.unlink(missing_ok=True)
            os.link(current, link)
            os.replace(link, run_dir / PREVIOUS_CHECKPOINT)


def common_checkpoints(run_dirs: list[Path], resuming: list[bool]) -> list[Path | None]:
    """The checkpoint each seed of a ``seeds=[...]`` run continues from (``None``: none resumes): the last step
    that every seed has a checkpoint of, its current or its previous one (:func:`keep_previous_checkpoints`).

    Raises:
        CheckpointError: some seeds have a checkpoint and others none, or they share no step.
    """
    if not any(resuming):
        return [None] * len(run_dirs)
    if not all(resuming):
        missing = [str(d) for d, r in zip(run_dirs, resuming, strict=True) if not r]
        raise CheckpointError(f"no checkpoint to continue in {', '.join(missing)}, but in the other seeds'")
    steps = []
    for run_dir in run_dirs:
        found = {}
        for name in (CHECKPOINT_NAME, PREVIOUS_CHECKPOINT):
            if (run_dir / name).is_file():
                found.setdefault(int(load_checkpoint(run_dir / name)["step"]), run_dir / name)
        steps.append(found)
    shared = set.intersection(*(set(found) for found in steps))
    if not shared:
        raise CheckpointError(
            f"the seeds' checkpoints share no step ({[sorted(found) for found in steps]}); resume each seed on "
            "its own (hydra.run.dir=<its seed folder> seed=<k> resume=true)"
        )
    return [found[max(shared)] for found in steps]
