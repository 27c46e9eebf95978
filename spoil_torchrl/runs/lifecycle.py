"""A run of the main recipe from its settings to its trained-but-not-yet-optimised algorithm: claim the run
directory (:func:`~spoil_torchrl.runs.claim.claim_runs`, importable from here too), load the input of
Algorithm 1 for each seed (:func:`open_runs`) and pre-train what the algorithm needs (:func:`pretrain`).
:mod:`spoil_torchrl.runs.training` takes it from there. A user's own
recipe calls the same functions::

    with claim_runs(cfg, run_dir) as claim:
        if not claim.finished:
            runs = open_runs(claim)
            with recorded_failure(runs):
                pretrained = [pretrain(inputs) for inputs in runs]
                results = train_one(pretrained[0])
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from spoil_torchrl.algorithms import (
    ALGORITHMS,
    Algorithm,
    BuildContext,
    EpisodeConstraint,
    PolicyTraining,
    Pretraining,
)
from spoil_torchrl.data import (
    DualDemoBuffers,
    fit_observation_normalizer,
    segment_pools,
    standardize_observations,
)
from spoil_torchrl.data.prepare import prepare_dataset
from spoil_torchrl.devices import training_device
from spoil_torchrl.envs.cost_components import COMPONENT_NAMES, COST_COMPONENTS
from spoil_torchrl.errors import SettingsError
from spoil_torchrl.eval import Evaluator
from spoil_torchrl.eval.dice_diagnostics import subsample
from spoil_torchrl.runs.checkpoint import CheckpointError, load_checkpoint
from spoil_torchrl.runs.claim import Claim, claim_runs, seed_settings  # noqa: F401 (the first step, here too)
from spoil_torchrl.runs.directory import (
    RunDirError,
)
from spoil_torchrl.runs.pretraining import (
    PRETRAINING_NAME,
    check_same_data,
    data_fingerprint,
    load_pretraining,
    save_pretraining,
)
from spoil_torchrl.runs.results import experiment_cell, note_where, settings_yaml, write_json
from spoil_torchrl.runs.resume import (
    check_resumable,
    pretraining_fingerprint,
    trim_csv_logs,
)
from spoil_torchrl.runs.seed_run import (
    DiceProbe,
    PretrainedRun,
    RunInputs,
    performant_support,
)
from spoil_torchrl.runs.tracking import make_logger
from spoil_torchrl.stack import current_machine, current_stack
from spoil_torchrl.tasks import get_env_task


def _probe_checkpoint_folder(run_dir: Path) -> None:
    """An unwritable checkpoint folder fails now, not at the first evaluation."""
    probe = run_dir / "checkpoints" / ".writable"
    try:
        probe.parent.mkdir(parents=True, exist_ok=True)
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise RunDirError(f"{probe.parent}: cannot write checkpoints there ({err})") from None


def open_runs(claim: Claim) -> list[RunInputs]:
    """Input of Algorithm 1 for every seed of ``claim`` (:func:`open_run`), each seed's data loaded and its resume
    checked before any seed's files are written: a refused seed (a stored pre-training of other data) leaves every
    seed's run directory as it was."""
    loaded = [_load(cfg, run_dir, checkpoint, claim.start) for cfg, run_dir, checkpoint in claim.seeds]
    return [_record(one) for one in loaded]


def open_run(cfg: DictConfig, run_dir: Path, checkpoint: Path | None, start: float) -> RunInputs:
    """Input of Algorithm 1 for one seed: D_S, D_P, D_U and D_0 in their buffers, the evaluator, the logger, and
    ``results.json`` (or, resuming from ``checkpoint``, its state and results, and the run's stored pre-training
    written back into the buffers: :mod:`spoil_torchrl.runs.pretraining`). A resume that is refused (other
    settings, a damaged file, other data) changes nothing in the run directory."""
    return _record(_load(cfg, run_dir, checkpoint, start))


@dataclass(frozen=True)
class _Loaded:
    """One seed's run as loaded and checked, before anything is written into its directory."""

    cfg: DictConfig
    run_dir: Path
    config_yaml: str
    state: dict | None
    stored: Pretraining | None
    data: object
    norm: object
    buffers: DualDemoBuffers
    data_seconds: float
    evaluator: Evaluator
    random_state: torch.Tensor
    start: float


def _load(cfg: DictConfig, run_dir: Path, checkpoint: Path | None, start: float) -> _Loaded:
    """Load one seed's run (its data in buffers, the checkpoint and stored pre-training it continues from, the
    evaluator) and check everything a resume can be refused for; writes nothing into the run directory."""
    torch.set_num_threads(int(cfg.threads))
    torch.manual_seed(int(cfg.seed))
    config_yaml = settings_yaml(cfg)
    state, stored = _resumed_from(cfg, run_dir, checkpoint, config_yaml)
    task = get_env_task(cfg.task.env_id)
    if cfg.train.checkpoint:
        _probe_checkpoint_folder(run_dir)
    data, norm, buffers = _load_buffers(cfg, task.env_id)
    if stored is not None:  # the resumed run's pre-training, as stored, on the same data
        check_same_data(run_dir / PRETRAINING_NAME, stored[1], buffers)
        stored[0].apply(buffers)
    data_seconds = time.perf_counter() - start
    evaluator = Evaluator(  # built (and its settings checked) before any training
        task.env_id,
        cost_threshold=data.cost_threshold,
        return_range=data.return_range,
        episodes=int(cfg.train.eval_episodes),
        seed=10_000 + int(cfg.seed),
        num_envs=int(cfg.task.eval_num_envs),
        frames=bool(OmegaConf.select(cfg, "eval.frames", default=False)),
        constraints=evaluated_constraints(cfg, task.env_id, data.cost_threshold),
    )
    stored = None if stored is None else stored[0]
    return _Loaded(
        cfg,
        run_dir,
        config_yaml,
        state,
        stored,
        data,
        norm,
        buffers,
        data_seconds,
        evaluator,
        torch.get_rng_state(),
        start,
    )


def _record(run: _Loaded) -> RunInputs:
    """Start writing a loaded run's record: ``config.yaml``, the TorchRL logger (labelled by dataset / algo /
    seed, the settings as hyper-parameters) and ``results.json`` (a resumed run's from its checkpoint, its logs
    cut back to the checkpoint's rows)."""
    cfg, run_dir, state = run.cfg, run.run_dir, run.state
    (run_dir / "config.yaml").write_text(run.config_yaml)
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
        env_id, summary = get_env_task(cfg.task.env_id).env_id, run.data.summary()
        results = _new_results(cfg, env_id, run.config_yaml, summary, run.data_seconds, tracking)
    write_json(run_dir / "results.json", results)
    return RunInputs(
        cfg,
        run_dir,
        results,
        run.buffers,
        run.evaluator,
        logger,
        run.norm,
        run.data.metadata,
        state,
        run.start,
        random_state=run.random_state,
        stored=run.stored,
    )


def evaluated_constraints(cfg: DictConfig, env_id: str, cost_threshold: float) -> dict[str, float] | None:
    """The thresholds of ``dataset.constraints`` (``dataset.constraint_thresholds``, else the cost threshold)
    for the evaluator, when the task computes per-constraint costs (``None`` otherwise: the task's cost only).
    ``+eval.constraints=[...]`` names them for a run that trains on the task's cost alone (e.g. the merged
    label beside a run with one safe set per constraint)."""
    asked = list(OmegaConf.select(cfg, "eval.constraints", default=None) or [])
    names = list(OmegaConf.select(cfg, "dataset.constraints", default=None) or asked)
    have = COMPONENT_NAMES.get(env_id, ())
    unknown = [name for name in asked if name not in have]
    if unknown:  # asked for by name: a task that cannot report them is an error, not a silent omission
        raise SettingsError(
            f"eval.constraints = {asked}: {env_id} reports the per-constraint costs of "
            f"{list(have) or 'no constraint'}; {unknown} are not among them"
        )
    if not names or env_id not in COST_COMPONENTS:
        return None
    given = dict(OmegaConf.select(cfg, "dataset.constraint_thresholds", default=None) or {})
    return {name: float(given.get(name, cost_threshold)) for name in names}


def _resumed_from(cfg: DictConfig, run_dir: Path, checkpoint: Path | None, config_yaml: str):
    """The checkpoint's content and the stored pre-training (with its record) a resumed run continues from,
    both checked against the settings; ``(None, None)`` for a run that starts, ``(state, None)`` for a run from
    before pre-trainings were stored."""
    if checkpoint is None:
        return None, None
    state = load_checkpoint(checkpoint)  # the checkpoint of an evaluation, made with the same settings
    check_resumable(state, config_yaml, run_dir)
    if not (run_dir / PRETRAINING_NAME).is_file():
        return state, None
    return state, load_pretraining(run_dir, config_yaml, algo=cfg.algo.name)


def _load_buffers(cfg: DictConfig, env_id: str):
    """The dataset's roles in their replay buffers, states standardised with D_U's statistics (every network
    reads them, the saved policy carries them); returns the prepared data, the statistics and the buffers."""
    # (an algorithm that needs another role, e.g. SafeDICE's non-preferred D_N, lists it in algo.extra_roles)
    data = prepare_dataset(
        cfg.dataset,
        env_id=env_id,
        seed=int(cfg.seed),
        progress=cfg.progress,
        extra_roles=tuple(cfg.algo.get("extra_roles", ())),
    )
    norm = (
        fit_observation_normalizer(data.episodes, data.roles["unlabeled"])
        if cfg.normalize_observations
        else None
    )
    episodes = data.episodes if norm is None else standardize_observations(data.episodes, norm)
    device = training_device(OmegaConf.select(cfg, "device", default=None))
    buffers = DualDemoBuffers(
        episodes, data.roles, batch_size=int(cfg.train.batch_size), seed=int(cfg.seed), device=device
    )
    return data, None if norm is None else norm.to(device), buffers


def _new_results(
    cfg: DictConfig, env_id: str, config_yaml: str, data: dict, data_seconds: float, tracking: dict | None
) -> dict:
    """The ``results.json`` of a run that starts: what it is, what it runs on, and no evaluation yet."""
    results = {
        "algo": cfg.algo.name,
        "dataset": cfg.dataset.name,
        "env_id": env_id,
        "seed": int(cfg.seed),
        "config_hash": hashlib.sha256(config_yaml.encode()).hexdigest()[:12],
        "stack": current_stack(),  # the versions that decide the numbers (spoil_torchrl.stack)
        "data": data,
        "status": "pre-training",
        "data_seconds": data_seconds,  # loading and preparing the data (pretrain_seconds includes it)
        "evaluations": [],
    }
    if experiment_cell(cfg) is not None:  # the cell of a paper experiment's sweep (its figure reads it)
        results["experiment"] = experiment_cell(cfg)
    if tracking:  # what a resumed run needs to continue the same tracked run (W&B's run id)
        results["tracking"] = tracking
    return results


def pretrain(inputs: RunInputs) -> PretrainedRun:
    """Pre-train what the algorithm needs (SpoilDICE: C_P, C_S, support cut, annotated D_U), from the seed's own
    random stream, store it in the run directory (with ``train.checkpoint``) and build the main stage on it. A
    resumed run builds its main stage on the pre-training it stored (:func:`open_run` wrote it back into the
    buffers) and trains nothing; a run from before pre-trainings were stored computes it again and checks that
    it reproduces the checkpoint's. Returns the run ready for its main stage."""
    cfg, results, state = inputs.cfg, inputs.results, inputs.checkpoint
    torch.set_rng_state(inputs.random_state)
    context = _build_context(inputs)
    algorithm = ALGORITHMS[cfg.algo.name]
    pretraining = inputs.stored  # loaded, its data and settings checked (open_run)
    if pretraining is None:
        pretraining = _pretrain_and_store(inputs, algorithm, context)
    training = replace(algorithm.main(cfg.algo, context, pretraining), observation_norm=inputs.norm)
    fingerprint = pretraining_fingerprint(inputs.buffers, training.diagnostics)
    # a pre-training computed again must reproduce the run's; a stored one is the run's (the main stage's own
    # float32 statistics, e.g. DemoDICE's reward mean, may round differently on another CPU)
    if state is not None and inputs.stored is None and fingerprint != state["pretraining"]:
        raise CheckpointError(
            f"{inputs.run_dir}: pre-training did not reproduce the run's (another machine, library version or "
            "dataset file?), so it cannot continue exactly; start a new run"
        )
    if state is None:
        results.update(diagnostics=training.diagnostics, pretrain_seconds=time.perf_counter() - inputs.start)
    # where the main stage runs from here, after how long: data and pre-training, or data and loading it
    step, setup = 0 if state is None else state["step"], time.perf_counter() - inputs.start
    note_where(results, current_machine(), "main", step, setup_seconds=setup)
    probe = _diagnostics_probe(inputs, training)
    return PretrainedRun(  # with where the main stage starts drawing
        inputs, pretraining, training, fingerprint, probe, random_state=torch.get_rng_state()
    )


def _build_context(inputs: RunInputs) -> BuildContext:
    """What the algorithm's stages are built from: the buffers, the task's dimensions and episode constraint."""
    task = get_env_task(inputs.cfg.task.env_id)
    return BuildContext(
        inputs.buffers,
        task.observation_dim,
        task.action_dim,
        # the dataset's episode-cost threshold over the task's horizon (read by COptiDICE and FBC's oracle)
        constraint=EpisodeConstraint(inputs.evaluator.cost_threshold, task.episode_length),
        logger=inputs.logger if inputs.checkpoint is None else None,
        progress=inputs.cfg.progress,
        device=inputs.buffers.device,
    )


def _diagnostics_probe(inputs: RunInputs, training: PolicyTraining) -> DiceProbe | None:
    """Diagnostics (never read by training): D_P's support estimate once, into ``results``, and for a DICE
    method a fixed subsample of its role on which (nu, lambda) are examined at every evaluation."""
    pools = segment_pools(inputs.metadata) if "segments" in inputs.metadata else None
    if pools is not None:  # beside the transitions they select
        pools = {name: ids.to(inputs.buffers.device) for name, ids in pools.items()}
    support = performant_support(inputs.buffers, pools)
    if support is not None:
        inputs.results["performant_support"] = support
    if training.dice is None:
        return None
    transitions = subsample(inputs.buffers[training.dice_role].storage[:], seed=int(inputs.cfg.seed))
    return DiceProbe(pools, support, transitions, inputs.buffers["init"].storage[:])


def _pretrain_and_store(inputs: RunInputs, algorithm: Algorithm, context: BuildContext) -> Pretraining:
    """The algorithm's pre-training, computed; a new run with checkpoints stores it (a resume loads it)."""
    cfg, fresh = inputs.cfg, inputs.checkpoint is None
    store = fresh and bool(cfg.train.checkpoint)
    data = data_fingerprint(inputs.buffers) if store else ""  # before the pre-training annotates them
    pretraining = algorithm.pretrain(cfg.algo, context)
    machine = current_machine()
    if store:
        config_yaml = (inputs.run_dir / "config.yaml").read_text()
        save_pretraining(
            inputs.run_dir,
            pretraining,
            config_yaml=config_yaml,
            data=data,
            algo=cfg.algo.name,
            machine=machine,
        )
    if fresh:
        note_where(inputs.results, machine, "pre-training")
    return pretraining
