"""The main job: train SpoilDICE (or a baseline, ``algo=``) on an offline dataset and evaluate it in the task.

    python recipes/spoildice_dsrl.py                     # SpoilDICE on the embedded PointCircle1 dataset
    python recipes/spoildice_dsrl.py algo=bc seed=1
    python recipes/spoildice_dsrl.py preset=smoke        # plumbing check, well under a minute
    python recipes/spoildice_dsrl.py preset=paper        # Table J: 1M iterations, lr 3e-5
    python recipes/spoildice_dsrl.py hydra.run.dir=<run dir> resume=true   # continue a killed run
    python recipes/spoildice_dsrl.py seeds=[0,1,2,3,4]   # five seeds' main stages in one vectorised step

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

``seeds=[...]`` runs every seed's Algorithm 1 in one process: input and pre-training seed after seed, each from
its own random stream, then the main stages at once (``train_seeds``: the networks stacked along a seed
dimension, one vmapped, compiled update, :class:`~spoil_torchrl.trainers.vectorized.VectorizedStepper`). Each
seed writes a single-seed run's files, with its settings, into ``seed<k>/`` of the run directory.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import time
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf, open_dict
from torch import nn

from spoil_torchrl.data import (
    DualDemoBuffers,
    fit_observation_normalizer,
    segment_pools,
    standardize_observations,
)
from spoil_torchrl.data.collect import ROLLOUT_MODULES
from spoil_torchrl.data.parallel import RolloutPool, available_cores
from spoil_torchrl.data.prepare import prepare_dataset
from spoil_torchrl.envs import log_mujoco_warnings
from spoil_torchrl.eval import Evaluator
from spoil_torchrl.eval.dice_diagnostics import subsample
from spoil_torchrl.eval.evaluator import METRICS
from spoil_torchrl.precision import matmul_precision
from spoil_torchrl.stack import current_stack
from spoil_torchrl.tasks import get_env_task
from spoil_torchrl.trainers import CompiledStepper, offline_trainer, stop_on_signals
from spoil_torchrl.trainers.algorithms import ALGORITHMS, EpisodeConstraint
from spoil_torchrl.trainers.checkpoint import (
    CheckpointError,
    load_checkpoint,
    rng_state,
    set_rng_state,
)
from spoil_torchrl.trainers.outcome import ended_in_one_line, is_sweep_job
from spoil_torchrl.trainers.resume import (
    check_resumable,
    finished_already,
    pretraining_fingerprint,
    trim_csv_logs,
)
from spoil_torchrl.trainers.run_dir import (
    CHECKPOINT_NAME,
    RunDirError,
    claim_run_dir,
    release_run_dir,
    write_hydra_record,
)
from spoil_torchrl.trainers.run_results import experiment_cell, settings_yaml, summary_table, write_json
from spoil_torchrl.trainers.seed_run import (
    SeedRun,
    common_checkpoints,
    evaluate,
    evaluation_due,
    finish,
    keep_previous_checkpoints,
    main_stage_clock,
    note_precision,
    performant_support,
    recorded_failure,
    rollout_job,
    rollout_writer,
    save_state,
)
from spoil_torchrl.trainers.settings import SettingsError, check_settings, name_dataset_by_source
from spoil_torchrl.trainers.tracking import check_logger_available, make_logger
from spoil_torchrl.trainers.vectorized import VectorizedStepper

log = logging.getLogger(__name__)


def run(cfg: DictConfig, run_dir: Path) -> dict | list[dict]:
    """Train and evaluate as configured (or continue the run in ``run_dir``, ``resume=true``); returns the
    content of ``results.json`` (one per seed, in ``seed<k>/``, for ``seeds=[...]``), or ``[]`` when
    ``resume=auto`` finds the run finished with these settings."""
    start = time.perf_counter()
    check_settings(OmegaConf.to_container(cfg, resolve=True))  # before any data loading or training
    check_logger_available(cfg.logger.type)  # a missing tensorboard / wandb fails now, not after pre-training
    if cfg.algo.name not in ALGORITHMS:
        raise SettingsError(f"algo.name={cfg.algo.name!r} has no builder; available: {', '.join(ALGORITHMS)}")
    seeds = cfg.get("seeds")
    resume = cfg.get("resume", False)
    done = [  # resume=auto passes over runs that have finished with these settings (a sweep's finished cells)
        finished_already(
            run_dir / f"seed{s}" if seeds else run_dir, settings_yaml(seed_settings(cfg, s)), resume
        )
        for s in (seeds or [cfg.seed])
    ]
    if all(done):  # said on the console only: the finished run's files stay as they are
        print(f"{run_dir}: finished already; nothing to do (resume=auto)")
        return []

    # never starts over a run (a seeds=[...] run keeps its runs in seed<k>/, each claimed on its own)
    def same_settings(resuming: bool) -> None:  # a refused resume writes nothing into the run directory
        if resuming and not seeds:
            check_resumable(load_checkpoint(run_dir / CHECKPOINT_NAME), settings_yaml(cfg), run_dir)

    resuming = claim_run_dir(run_dir, resume="auto" if seeds and resume else resume, check=same_settings)
    if not resuming:
        write_hydra_record(run_dir, cfg)
    try:
        if seeds:
            return run_seeds(cfg, run_dir, [int(s) for s in seeds], start)
        seed_run = open_run(cfg, run_dir, run_dir / CHECKPOINT_NAME if resuming else None, start)
        with recorded_failure([seed_run]), matmul_precision(cfg.train.get("matmul_precision", "highest")):
            note_precision([seed_run])  # training's float32 products as configured; every rollout's are IEEE
            pretrain(seed_run)
            return train_one(seed_run)
    finally:
        release_run_dir(run_dir)


def open_run(cfg: DictConfig, run_dir: Path, checkpoint: Path | None, start: float) -> SeedRun:
    """Input of Algorithm 1 for one seed: D_S, D_P, D_U and D_0 in their buffers, the evaluator, the logger, and
    ``results.json`` (or, resuming from ``checkpoint``, its state and results)."""
    torch.set_num_threads(int(cfg.threads))
    torch.manual_seed(int(cfg.seed))
    config_yaml = settings_yaml(cfg)
    state = None
    if checkpoint is not None:  # the checkpoint of an evaluation, made with the same settings
        state = load_checkpoint(checkpoint)
        check_resumable(state, config_yaml, run_dir)
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
            "stack": current_stack(),  # the versions that decide the numbers (spoil_torchrl.stack)
            "data": data.summary(),
            "status": "pre-training",
            "data_seconds": data_seconds,  # loading and preparing the data (pretrain_seconds includes it)
            "evaluations": [],
        }
        if experiment_cell(cfg) is not None:  # the cell of a paper experiment's sweep (its figure reads it)
            results["experiment"] = experiment_cell(cfg)
        if tracking:  # what a resumed run needs to continue the same tracked run (W&B's run id)
            results["tracking"] = tracking
    write_json(run_dir / "results.json", results)
    seed_run = SeedRun(cfg, run_dir, results, buffers, evaluator, logger, norm, data.metadata, state, start)
    seed_run.random_state = torch.get_rng_state()
    return seed_run


def pretrain(seed_run: SeedRun) -> None:
    """Pre-train what the algorithm needs (SpoilDICE: C_P, C_S, support cut, annotated D_U), from the seed's own
    random stream. A resumed run does it again, deterministically, and checks that it got the same (no second
    log rows)."""
    cfg, results, buffers, state = seed_run.cfg, seed_run.results, seed_run.buffers, seed_run.state
    task = get_env_task(cfg.task.env_id)
    torch.set_rng_state(seed_run.random_state)
    pools = segment_pools(seed_run.metadata) if "segments" in seed_run.metadata else None
    # (the constraint, the dataset's episode-cost threshold over the task's horizon, is read by COptiDICE only)
    training = ALGORITHMS[cfg.algo.name](
        cfg.algo,
        buffers,
        task.observation_dim,
        task.action_dim,
        constraint=EpisodeConstraint(seed_run.evaluator.cost_threshold, task.episode_length),
        logger=seed_run.logger if state is None else None,
        progress=cfg.progress,
    )
    training.observation_norm = seed_run.norm
    fingerprint = pretraining_fingerprint(buffers, training.diagnostics)
    if state is not None and fingerprint != state["pretraining"]:
        raise CheckpointError(
            f"{seed_run.run_dir}: pre-training did not reproduce the run's (another machine, library version or "
            "dataset file?), so it cannot continue exactly; start a new run"
        )
    if state is None:
        results.update(
            diagnostics=training.diagnostics, pretrain_seconds=time.perf_counter() - seed_run.start
        )
    # Diagnostics (never read by training): D_P's support estimate once, and a fixed subsample of the DICE
    # role on which (nu, lambda) are examined at every evaluation.
    support = performant_support(buffers, pools)
    if support is not None:
        results["performant_support"] = support
    extras = {"pools": pools, "support": support}
    if training.dice is not None:
        extras["probe"] = subsample(buffers[training.dice_role].storage[:], seed=int(cfg.seed))
        extras["probe_init"] = buffers["init"].storage[:]
    seed_run.training, seed_run.fingerprint, seed_run.extras = training, fingerprint, extras
    seed_run.random_state = torch.get_rng_state()  # where the main stage starts drawing


def train_one(seed_run: SeedRun) -> dict:
    """Optimise the main stage with the TorchRL Trainer, evaluating every ``train.eval_interval`` steps."""
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
        steps_per_batch=math.gcd(int(train.eval_interval), int(train.steps), 100),
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


def seed_settings(cfg: DictConfig, seed: int) -> DictConfig:
    """The settings of seed ``seed`` of a ``seeds=[...]`` run: the single-seed run's (``seed=<seed>``)."""
    seed_cfg = cfg.copy()
    with open_dict(seed_cfg):
        seed_cfg.seed, seed_cfg.seeds = int(seed), None
    return seed_cfg


def run_seeds(cfg: DictConfig, run_dir: Path, seeds: list[int], start: float) -> list[dict]:
    """``seeds=[...]``: every seed's run in ``run_dir/seed<k>`` (the files of a single-seed run, its settings),
    pre-trained one after another, the main stages trained at once by one :class:`VectorizedStepper`."""
    (run_dir / "config.yaml").write_text(settings_yaml(cfg))
    claimed, resuming = [], []
    try:
        for seed in seeds:
            claimed.append(run_dir / f"seed{seed}")
            resuming.append(claim_run_dir(claimed[-1], resume=cfg.get("resume", False)))
        checkpoints = common_checkpoints(claimed, resuming)  # the last step every seed can continue from
        runs = [
            open_run(seed_settings(cfg, seed), seed_dir, checkpoint, start)
            for seed, seed_dir, checkpoint in zip(seeds, claimed, checkpoints, strict=True)
        ]
        with recorded_failure(runs), matmul_precision(cfg.train.get("matmul_precision", "highest")):
            note_precision(runs)
            for seed_run in runs:
                pretrain(seed_run)
            return train_seeds(runs)
    finally:
        for seed_dir in claimed:
            release_run_dir(seed_dir)


def train_seeds(runs: list[SeedRun]) -> list[dict]:
    """The main stage of every seed at once: one Trainer, one vmapped update; each seed evaluated, logged and
    checkpointed as its own run."""
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
        steps_per_batch=math.gcd(int(train.eval_interval), int(train.steps), 100),
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


@hydra.main(config_path="../configs", config_name="spoildice_dsrl", version_base="1.3")
def main(cfg: DictConfig) -> None:
    stop_on_signals()  # SIGTERM ends the run like Ctrl-C: marked "interrupted", its checkpoint intact
    logging.captureWarnings(True)  # warnings about the data or settings also go into the run's log
    log_mujoco_warnings()  # into the run's log, not MUJOCO_LOG.TXT in the working directory
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    name_dataset_by_source(cfg, HydraConfig.get().overrides.task)  # runs of another file get its name
    # a user's error, divergence, Ctrl-C; a sweep goes on past a diverged cell (recorded as failed)
    results = []
    with ended_in_one_line("recipes/spoildice_dsrl.py", run_dir, keep_going=is_sweep_job()):
        results = run(cfg, run_dir)
    if not results:  # passed over (finished already) or, in a sweep, diverged: said in one line
        return
    for one in results if isinstance(results, list) else [results]:
        log.info(summary_table(one))
        if "dice_report" in one:
            log.info(f"\n{one['dice_report']}")
    log.info(f"\nrun directory: {run_dir}")


if __name__ == "__main__":
    main()
