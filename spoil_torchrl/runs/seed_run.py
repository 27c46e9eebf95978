"""One seed's run of the main recipe: what it holds (:class:`SeedRun`) and the bookkeeping every run does the
same way, alone or as one of the seeds of a ``seeds=[...]`` run: evaluate the policy and rewrite
``results.json`` (:func:`evaluate`), checkpoint (:func:`save_state`), write its MCAP file
(:func:`rollout_writer`), record why it stopped (:func:`recorded_failure`) and finish with the paper's aggregate
(:func:`finish`). The recipe (``recipes/spoildice_dsrl.py``) reads like Algorithm 1 and calls these.
"""

from __future__ import annotations

import contextlib
import copy
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
from omegaconf import DictConfig

from spoil_torchrl.algorithms import PolicyTraining, Pretraining
from spoil_torchrl.data import DualDemoBuffers
from spoil_torchrl.data.parallel import Job
from spoil_torchrl.divergence import check_finite
from spoil_torchrl.eval import Evaluator, RolloutWriter
from spoil_torchrl.eval.dice_diagnostics import (
    dice_diagnostics,
    explain,
    source_masks,
    summary_scalars,
    support_accuracy,
)
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


@dataclass
class SeedRun:
    """One seed's run: its settings, directory, data, evaluator, logger and ``results.json`` content, and, once
    the recipe has pre-trained it, the algorithm's training (``training``) and the diagnostics' fixed inputs."""

    cfg: DictConfig
    run_dir: Path
    results: dict
    buffers: DualDemoBuffers
    evaluator: Evaluator
    logger: object
    norm: object
    metadata: dict
    state: dict | None  # the checkpoint continued from (resume), else None
    start: float
    random_state: torch.Tensor | None = None  # torch's generator where this seed's run has got to
    pretraining: Pretraining | None = None  # the algorithm's pre-training (stored by the run, or loaded)
    training: PolicyTraining | None = None
    fingerprint: str = ""
    extras: dict = field(default_factory=dict)  # pools, support estimate, diagnostics' probe


@contextlib.contextmanager
def recorded_failure(runs: list[SeedRun]):
    """Keep what was done: on any error or interruption every run's ``results.json`` says why it stopped."""
    try:
        yield
    except BaseException as err:
        for seed_run in runs:
            seed_run.results["status"] = "interrupted" if isinstance(err, KeyboardInterrupt) else "failed"
            seed_run.results["error"] = f"{type(err).__name__}: {err}"
            write_json(seed_run.run_dir / "results.json", seed_run.results)
        raise


def note_precision(runs: list[SeedRun]) -> None:
    """Record the matmul precision training runs at, and its measured error, in every run's results."""
    error = matmul_check()  # as this machine computes them
    for seed_run in runs:
        seed_run.results["matmul_precision"] = torch.get_float32_matmul_precision()
        seed_run.results["matmul_relative_error"] = error


def performant_support(buffers, pools) -> dict | None:
    """The support estimate on D_P against the true cost (``None`` where the algorithm annotated none)."""
    if "performant" not in buffers.roles:
        return None
    performant = buffers["performant"].storage[:]
    if "safe_support" not in performant.keys():
        return None
    groups = source_masks(performant["episode"], pools)
    return support_accuracy(performant["safe_support"], performant["next", "cost"], groups)


def rollout_job(seed_run: SeedRun) -> Job:
    """The evaluation rollout of the seed's current policy (a copy) as a job for a
    :class:`~spoil_torchrl.data.parallel.RolloutPool`."""
    with seed_run.training.policy() as policy:
        return seed_run.evaluator.rollout_job(copy.deepcopy(policy))


def evaluate(
    seed_run: SeedRun,
    step: int,
    train_start: float,
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
    cfg, results, training = seed_run.cfg, seed_run.results, seed_run.training
    evaluation_start = time.perf_counter() if started is None else started
    with training.policy() as policy:
        for name, weight in policy.named_parameters():  # a diverged policy is never evaluated
            check_finite(f"policy weight {name}", weight.detach(), f"step {step}", DIVERGED_ADVICE)
        result = (
            seed_run.evaluator(policy, step) if rollout is None else seed_run.evaluator.report(rollout, step)
        )
        if cfg.train.checkpoint:
            save_policy(
                seed_run.run_dir / "checkpoints" / "policy.pt",
                policy,
                env_id=cfg.task.env_id,
                distribution=cfg.algo.distribution,
                info={"step": step, "algo": cfg.algo.name, "config_hash": results["config_hash"]},
            )
    if training.dice is not None:
        x = seed_run.extras
        dice = dice_diagnostics(
            training.dice, x["probe"], x["probe_init"], role=training.dice_role, pools=x["pools"]
        )
        result["dice"] = summary_scalars(dice)
        results.update(dice_diagnostics=dice, dice_report=explain(dice, x["support"]))
        if seed_run.logger is not None:
            for key, value in result["dice"].items():
                seed_run.logger.log_scalar(key, value, step=step)
    result["seconds"] = time.perf_counter() - train_start
    result["eval_seconds"] = time.perf_counter() - evaluation_start  # rollouts, policy file, diagnostics
    results["evaluations"].append(result)
    write_json(seed_run.run_dir / "results.json", results)
    return result


def save_state(
    seed_run: SeedRun, step: int, trainer_state: dict, random_state: dict, train_start: float
) -> None:
    """After an evaluation and its log rows: everything the seed's run needs to continue from here."""
    save_checkpoint(
        seed_run.run_dir / CHECKPOINT_NAME,
        {
            "step": step,
            "config_yaml": (seed_run.run_dir / "config.yaml").read_text(),
            "trainer": trainer_state,
            "stepper": trainer_state["optimization_stepper"],
            "rng": random_state,
            "results": seed_run.results,
            "pretraining": seed_run.fingerprint,
            "csv_rows": csv_row_counts(seed_run.run_dir / "logs"),
            "train_seconds": time.perf_counter() - train_start,
            "total_seconds": time.perf_counter() - seed_run.start,
        },
    )
    write_lock(seed_run.run_dir)  # heartbeat


def finish(seed_run: SeedRun, update_step: str, train_start: float) -> dict:
    """Output: ``results.json`` with the paper's aggregate of the last evaluations."""
    results = seed_run.results
    last = min(int(seed_run.cfg.train.last_evaluations), len(results["evaluations"]))
    results.update(
        status="finished",
        aggregate=aggregate(results["evaluations"], last),
        last_evaluations=last,
        update_step=update_step,
        train_seconds=time.perf_counter() - train_start,
        total_seconds=time.perf_counter() - seed_run.start,
    )
    write_json(seed_run.run_dir / "results.json", results)
    return results


def main_stage_clock(seed_run: SeedRun) -> float:
    """The main stage's start (a resumed run counts the time before its checkpoint); shifts the run's start."""
    state = seed_run.state
    if state is not None:
        seed_run.start -= state["total_seconds"]
    return time.perf_counter() - (0.0 if state is None else state["train_seconds"])


def rollout_writer(seed_run: SeedRun):
    """The seed's MCAP writer: a new file, or the run's file continued after the checkpoint's step."""
    cfg, results = seed_run.cfg, seed_run.results
    metadata = {
        "task": cfg.task.env_id,
        "algo": cfg.algo.name,
        "seed": cfg.seed,
        "config_hash": results["config_hash"],
    }
    mcap = dict(
        path=seed_run.run_dir / "rollouts.mcap",
        cost_threshold=seed_run.evaluator.cost_threshold,
        metadata=metadata,
    )
    if seed_run.state is None:
        return RolloutWriter(**mcap)
    return continue_rollouts(**mcap, until_step=seed_run.state["step"])


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
