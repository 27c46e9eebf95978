"""The main job: train SpoilDICE (or a baseline, ``algo=``) on an offline dataset and evaluate it in the task.

    python recipes/spoildice_dsrl.py                     # SpoilDICE on the embedded PointCircle1 dataset
    python recipes/spoildice_dsrl.py algo=bc seed=1
    python recipes/spoildice_dsrl.py preset=smoke        # plumbing check, well under a minute
    python recipes/spoildice_dsrl.py preset=paper        # Table J: 1M iterations, lr 3e-5
    python recipes/spoildice_dsrl.py hydra.run.dir=<run dir> resume=true   # continue a killed run

Reads like Algorithm 1 of the paper:

1. Input: D_S, D_P, D_U and the initial states, in one TorchRL replay buffer each (``DualDemoBuffers``),
   states standardised with D_U's mean and standard deviation (``normalize_observations``).
2. Pre-train C_P and C_S, fit the support cut, annotate D_U once (inside the algorithm's builder,
   ``spoil_torchrl.trainers.algorithms``).
3. Optimise (nu, lambda) and pi with ``torchrl.trainers.Trainer``, evaluating every ``train.eval_interval``
   steps in the real environment.
4. Output: the run directory holds ``config.yaml`` (resolved), ``logs/`` (TorchRL logger), ``checkpoints/``,
   ``results.json`` (every evaluation, raw and normalised, and the paper's aggregate; for DICE methods the
   diagnostics of ``spoil_torchrl.eval.dice_diagnostics`` at every evaluation and a text report at the end)
   and ``rollouts.mcap`` (every evaluation episode; ``python -m spoil_torchrl.inspect <file>``).
   ``results.json`` is rewritten after every evaluation and the MCAP file is flushed after every episode, so an
   interrupted run keeps both; ``checkpoints/training_state.pt`` lets it continue exactly (``resume=true``).
   A start never overwrites a run: the directory is claimed first (``spoil_torchrl.trainers.run_dir``).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import sys
import time
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from spoil_torchrl.data import (
    DualDemoBuffers,
    fit_observation_normalizer,
    segment_pools,
    standardize_observations,
)
from spoil_torchrl.data.episodes import DatasetError
from spoil_torchrl.data.prepare import prepare_dataset
from spoil_torchrl.eval import Evaluator, RolloutWriter
from spoil_torchrl.eval.dice_diagnostics import (
    dice_diagnostics,
    explain,
    source_masks,
    subsample,
    summary_scalars,
    support_accuracy,
)
from spoil_torchrl.eval.evaluator import METRICS
from spoil_torchrl.eval.mcap_resume import continue_rollouts
from spoil_torchrl.experts import save_policy
from spoil_torchrl.files import write_atomic
from spoil_torchrl.tasks import UnknownDatasetError, get_env_task
from spoil_torchrl.trainers import CompiledStepper, offline_trainer, stop_on_signals
from spoil_torchrl.trainers.algorithms import ALGORITHMS, EpisodeConstraint
from spoil_torchrl.trainers.checkpoint import (
    CheckpointError,
    load_checkpoint,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from spoil_torchrl.trainers.precision import (
    REDUCED_PRECISION_ERROR,
    matmul_precision,
    matmul_relative_error,
)
from spoil_torchrl.trainers.resume import (
    csv_row_counts,
    pretraining_fingerprint,
    settings_differ,
    trim_csv_logs,
)
from spoil_torchrl.trainers.run_dir import (
    CHECKPOINT_NAME,
    RunDirError,
    claim_run_dir,
    release_run_dir,
    write_lock,
)
from spoil_torchrl.trainers.settings import SettingsError, check_settings
from spoil_torchrl.trainers.tracking import check_logger_available, make_logger

log = logging.getLogger(__name__)


def _json_safe(value):
    """NaN / inf are not JSON: write them as null."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def write_json(path: Path, payload: dict) -> None:
    """Write ``payload`` atomically (a reader never sees half a file)."""
    write_atomic(path, json.dumps(_json_safe(payload), indent=2, allow_nan=False))


def aggregate(evaluations: list[dict], last: int) -> dict:
    """The paper's per-run aggregate: each metric's mean over the last ``last`` evaluations."""
    tail = evaluations[-last:]
    return {key: sum(e[key] for e in tail) / len(tail) for key in METRICS}


def matmul_check() -> float:
    """The relative error of float32 products at the run's matmul precision; a warning when they lose precision
    (``train.matmul_precision=medium`` on a CPU whose oneDNN takes bfloat16 kernels, e.g. one with AMX)."""
    error = matmul_relative_error()
    if error > REDUCED_PRECISION_ERROR:
        log.warning(
            f"train.matmul_precision={torch.get_float32_matmul_precision()}: float32 products lose precision on "
            f"this machine (relative error {error:.1e}: bfloat16 kernels); train.matmul_precision=highest keeps "
            "them IEEE float32"
        )
    return error


def settings_yaml(cfg: DictConfig) -> str:
    """The resolved settings as written to ``config.yaml`` (``resume`` left out: it says how to start, not
    what to train)."""
    settings = OmegaConf.to_container(cfg, resolve=True)
    settings.pop("resume", None)
    return OmegaConf.to_yaml(OmegaConf.create(settings))


def run(cfg: DictConfig, run_dir: Path) -> dict:
    """Train and evaluate as configured (or continue the run in ``run_dir``, ``resume=true``); returns the
    content of ``results.json``."""
    start = time.perf_counter()
    check_settings(OmegaConf.to_container(cfg, resolve=True))  # before any data loading or training
    check_logger_available(cfg.logger.type)  # a missing tensorboard / wandb fails now, not after pre-training
    if cfg.algo.name not in ALGORITHMS:
        raise SettingsError(f"algo.name={cfg.algo.name!r} has no builder; available: {', '.join(ALGORITHMS)}")
    resuming = claim_run_dir(run_dir, resume=cfg.get("resume", False))  # never starts over a run
    try:
        return _run(cfg, run_dir, resuming, start)
    finally:
        release_run_dir(run_dir)


def _run(cfg: DictConfig, run_dir: Path, resuming: bool, start: float) -> dict:
    torch.set_num_threads(int(cfg.threads))
    torch.manual_seed(int(cfg.seed))
    config_yaml = settings_yaml(cfg)
    state = None
    if resuming:  # the checkpoint of the last evaluation, made with the same settings
        state = load_checkpoint(run_dir / CHECKPOINT_NAME)
        differ = settings_differ(state["config_yaml"], config_yaml)
        if differ:
            raise CheckpointError(
                f"{run_dir}: resume=true with other settings than the run's ({', '.join(differ)}); resume "
                "with the run's own settings (its config.yaml) or start a new run"
            )
    (run_dir / "config.yaml").write_text(config_yaml)
    config_hash = hashlib.sha256(config_yaml.encode()).hexdigest()[:12]
    task = get_env_task(cfg.task.env_id)
    train = cfg.train
    if train.checkpoint:  # an unwritable checkpoint folder fails now, not at the first evaluation
        probe = run_dir / "checkpoints" / ".writable"
        try:
            probe.parent.mkdir(parents=True, exist_ok=True)
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as err:
            raise RunDirError(f"{probe.parent}: cannot write checkpoints there ({err})") from None

    # Input: D_S, D_P, D_U (episode ids of one dataset) and the initial states D_0.
    # (an algorithm that needs another role, e.g. SafeDICE's non-preferred D_N, lists it in algo.extra_roles)
    data = prepare_dataset(
        cfg.dataset,
        env_id=task.env_id,
        seed=int(cfg.seed),
        progress=cfg.progress,
        extra_roles=tuple(cfg.algo.get("extra_roles", ())),
    )
    obs_dim, act_dim = data.episodes["observation"].shape[-1], data.episodes["action"].shape[-1]
    if (obs_dim, act_dim) != (task.observation_dim, task.action_dim):
        raise ValueError(
            f"{cfg.dataset.source}: observation/action sizes {obs_dim}/{act_dim}, but {task.env_id} has "
            f"{task.observation_dim}/{task.action_dim}"
        )
    # States standardised once with D_U's statistics: every network reads them, the saved policy carries them.
    norm = (
        fit_observation_normalizer(data.episodes, data.roles["unlabeled"])
        if cfg.normalize_observations
        else None
    )
    episodes = data.episodes if norm is None else standardize_observations(data.episodes, norm)
    buffers = DualDemoBuffers(episodes, data.roles, batch_size=int(train.batch_size), seed=int(cfg.seed))
    data_seconds = time.perf_counter() - start
    evaluator = Evaluator(  # built (and its settings checked) before any training
        task.env_id,
        cost_threshold=data.cost_threshold,
        return_range=data.return_range,
        episodes=int(train.eval_episodes),
        seed=10_000 + int(cfg.seed),
        num_envs=int(cfg.task.eval_num_envs),
        frames=bool(OmegaConf.select(cfg, "eval.frames", default=False)),
    )
    # TorchRL logger, labelled by dataset / algo / seed, with the settings as hyper-parameters
    logger, tracking = make_logger(
        OmegaConf.to_container(cfg, resolve=True),
        run_dir / "logs",
        tracking=None if state is None else state["results"].get("tracking"),
    )
    if state is not None:  # the evaluations so far; the logs lose what was logged after the checkpoint
        results = state["results"]
        results.setdefault("resumed_at", []).append(int(state["step"]))
        trim_csv_logs(run_dir / "logs", state["csv_rows"])
    else:
        results = {
            "algo": cfg.algo.name,
            "dataset": cfg.dataset.name,
            "env_id": task.env_id,
            "seed": int(cfg.seed),
            "config_hash": config_hash,
            "data": data.summary(),
            "status": "pre-training",
            "data_seconds": data_seconds,  # loading and preparing the data (pretrain_seconds includes it)
            "evaluations": [],
        }
        if tracking:  # what a resumed run needs to continue the same tracked run (W&B's run id)
            results["tracking"] = tracking
    write_json(run_dir / "results.json", results)

    try:  # training's float32 products as configured (the data are ready; every rollout computes IEEE products)
        pools = segment_pools(data.metadata) if "segments" in data.metadata else None
        with matmul_precision(train.get("matmul_precision", "highest")):
            results["matmul_precision"] = torch.get_float32_matmul_precision()
            results["matmul_relative_error"] = matmul_check()  # as this machine computes them
            return _train(cfg, run_dir, results, buffers, evaluator, logger, norm, pools, start, state)
    except BaseException as err:  # keep what was done, say why it stopped, re-raise
        results["status"] = "interrupted" if isinstance(err, KeyboardInterrupt) else "failed"
        results["error"] = f"{type(err).__name__}: {err}"
        write_json(run_dir / "results.json", results)
        raise


def performant_support(buffers, pools) -> dict | None:
    """The support estimate on D_P against the true cost (``None`` where the algorithm annotated none)."""
    if "performant" not in buffers.roles:
        return None
    performant = buffers["performant"].storage[:]
    if "safe_support" not in performant.keys():
        return None
    groups = source_masks(performant["episode"], pools)
    return support_accuracy(performant["safe_support"], performant["next", "cost"], groups)


def _train(cfg, run_dir, results, buffers, evaluator, logger, norm, pools, start, state) -> dict:
    task, train, config_hash = get_env_task(cfg.task.env_id), cfg.train, results["config_hash"]
    obs_dim, act_dim = task.observation_dim, task.action_dim

    # Pre-train what the algorithm needs (SpoilDICE: C_P, C_S, support cut, annotated D_U).
    # (the constraint, the dataset's episode-cost threshold over the task's horizon, is read by COptiDICE only)
    # A resumed run does it again, deterministically, and checks that it got the same (no second log rows).
    training = ALGORITHMS[cfg.algo.name](
        cfg.algo,
        buffers,
        obs_dim,
        act_dim,
        constraint=EpisodeConstraint(evaluator.cost_threshold, task.episode_length),
        logger=logger if state is None else None,
        progress=cfg.progress,
    )
    training.observation_norm = norm
    fingerprint = pretraining_fingerprint(buffers, training.diagnostics)
    if state is not None and fingerprint != state["pretraining"]:
        raise CheckpointError(
            f"{run_dir}: pre-training did not reproduce the run's (another machine, library version or "
            "dataset file?), so it cannot continue exactly; start a new run"
        )
    if state is None:
        results.update(diagnostics=training.diagnostics, pretrain_seconds=time.perf_counter() - start)
    # Diagnostics (never read by training): D_P's support estimate once, and a fixed subsample of the DICE
    # role on which (nu, lambda) are examined at every evaluation.
    support = performant_support(buffers, pools)
    if support is not None:
        results["performant_support"] = support
    if training.dice is not None:
        probe = subsample(buffers[training.dice_role].storage[:], seed=int(cfg.seed))
        probe_init = buffers["init"].storage[:]

    # Optimise the main stage with the TorchRL Trainer; evaluate every eval_interval steps.
    checkpoints = run_dir / "checkpoints"
    total, interval = int(train.steps), int(train.eval_interval)
    results["status"] = "training"
    train_start = time.perf_counter() - (0.0 if state is None else state["train_seconds"])
    start -= 0.0 if state is None else state["total_seconds"]

    def evaluate(batch) -> dict | None:
        step = trainer.collected_frames
        if step % interval and step < total:
            return None
        evaluation_start = time.perf_counter()
        with training.policy() as policy:
            result = evaluator(policy, step)
            if train.checkpoint:
                save_policy(
                    checkpoints / "policy.pt",
                    policy,
                    env_id=task.env_id,
                    distribution=cfg.algo.distribution,
                    info={"step": step, "algo": cfg.algo.name, "config_hash": config_hash},
                )
        if training.dice is not None:
            dice = dice_diagnostics(training.dice, probe, probe_init, role=training.dice_role, pools=pools)
            result["dice"] = summary_scalars(dice)
            results.update(dice_diagnostics=dice, dice_report=explain(dice, support))
            if logger is not None:
                for key, value in result["dice"].items():
                    logger.log_scalar(key, value, step=step)
        result["seconds"] = time.perf_counter() - train_start
        result["eval_seconds"] = time.perf_counter() - evaluation_start  # rollouts, policy file, diagnostics
        trainer.progress.note(
            f"step {step}: feasible return {result['normalized_feasible_return']:.2f}, "
            f"cost {result['normalized_cost']:.2f}"
        )
        results["evaluations"].append(result)
        write_json(run_dir / "results.json", results)
        return {f"eval/{key}": result[key] for key in METRICS}

    def checkpoint(batch) -> None:
        """After the evaluation and its log rows: everything a resumed run needs to continue from here."""
        step = trainer.collected_frames
        if not train.checkpoint or not results["evaluations"] or results["evaluations"][-1]["step"] != step:
            return
        save_checkpoint(
            run_dir / CHECKPOINT_NAME,
            {
                "step": step,
                "config_yaml": (run_dir / "config.yaml").read_text(),
                "trainer": trainer.state_dict(),
                "stepper": training.stepper.state_dict(),
                "rng": rng_state(buffers),
                "results": results,
                "pretraining": fingerprint,
                "csv_rows": csv_row_counts(run_dir / "logs"),
                "train_seconds": time.perf_counter() - train_start,
                "total_seconds": time.perf_counter() - start,
            },
        )
        write_lock(run_dir)  # heartbeat

    if train.compile:  # the whole update as one compiled graph; says so and runs eagerly where it cannot
        training.stepper = CompiledStepper.from_stepper(training.stepper)
    trainer = offline_trainer(
        training.stepper,
        buffers.sample,
        total_steps=total,
        steps_per_batch=math.gcd(interval, total, 100),
        logger=logger,
        log_interval=int(train.log_interval),
        progress_bar=cfg.progress,
        progress_label=f"training {cfg.algo.name}",
    )
    trainer.register_op("post_steps_log", evaluate)
    trainer.register_op("post_steps_log", checkpoint)  # runs after the Trainer has logged the evaluation
    metadata = {"task": task.env_id, "algo": cfg.algo.name, "seed": cfg.seed, "config_hash": config_hash}
    mcap = dict(path=run_dir / "rollouts.mcap", cost_threshold=evaluator.cost_threshold, metadata=metadata)
    if state is not None:  # continue exactly where the checkpoint was taken
        trainer.load_state_dict(state["trainer"])
        training.stepper.load_state_dict(state["stepper"])
        set_rng_state(state["rng"], buffers)
    with RolloutWriter(**mcap) if state is None else continue_rollouts(**mcap, until_step=state["step"]) as w:
        evaluator.writer = w  # every evaluation episode goes to the MCAP file, flushed per episode
        trainer.train()

    # Output: results.json with the aggregate, and a small summary table.
    last = min(int(train.last_evaluations), len(results["evaluations"]))
    results.update(
        status="finished",
        aggregate=aggregate(results["evaluations"], last),
        last_evaluations=last,
        update_step="compiled" if getattr(training.stepper, "compiled", False) else "eager",
        train_seconds=time.perf_counter() - train_start,
        total_seconds=time.perf_counter() - start,
    )
    write_json(run_dir / "results.json", results)
    return results


def summary_table(results: dict) -> str:
    """The final evaluation and the aggregate of the main metrics, as markdown."""
    final = results["evaluations"][-1]
    lines = [
        f"{results['algo']} on {results['dataset']} (seed {results['seed']}), {final['step']} steps, "
        f"{results['total_seconds']:.0f} s",
        "",
        f"| metric | final evaluation | mean of last {results['last_evaluations']} |",
        "|---|---|---|",
    ]
    for key in ("normalized_feasible_return", "normalized_cost", "normalized_return", "return", "cost"):
        lines.append(f"| {key} | {final[key]:.3f} | {results['aggregate'][key]:.3f} |")
    return "\n".join(lines)


#: Errors that are the user's to fix (a setting, a file, a run directory): one message, no traceback
#: (``HYDRA_FULL_ERROR=1`` shows it).
USER_ERRORS = (SettingsError, RunDirError, CheckpointError, DatasetError, UnknownDatasetError)


@hydra.main(config_path="../configs", config_name="spoildice_dsrl", version_base="1.3")
def main(cfg: DictConfig) -> None:
    stop_on_signals()  # SIGTERM ends the run like Ctrl-C: marked "interrupted", its checkpoint intact
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        results = run(cfg, run_dir)
    except USER_ERRORS as err:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    log.info(summary_table(results))
    if "dice_report" in results:
        log.info(f"\n{results['dice_report']}")
    log.info(f"\nrun directory: {run_dir}")


if __name__ == "__main__":
    main()
