"""PPO and PPO-Lagrangian experts from TorchRL pieces, used to make demonstration data (paper F.2, Table G).

PPO-Lagrangian (Ray et al., 2019) adds a cost critic, a cost advantage (GAE on ``("next", "cost")``) and a
multiplier :math:`\\lambda \\ge 0` on the episode-cost limit :math:`d`: the policy maximises the surrogate of
:math:`(A_r - \\lambda A_c)/(1 + \\lambda)`, and after every batch :math:`\\lambda` takes one Adam step on
:math:`-\\lambda (\\bar C - d)` (then is clipped at 0), with :math:`\\bar C` the mean cost of the episodes
finished in the batch. The Adam step (OmniSafe's choice) moves :math:`\\lambda` by about ``lagrange_lr`` per
batch whatever the size of the violation; a plain gradient step with episode costs in the hundreds makes
:math:`\\lambda` explode (measured: 114 after 14 batches with rate 0.05) and the policy then ignores reward. With
``lagrangian=False`` it is plain PPO, and with ``cost_penalty`` :math:`\\beta > 0` as well, PPO on the reward
minus :math:`\\beta` times the cost: the same objective with the multiplier fixed at :math:`\\beta`.

Every batch starts from a reset seeded by the run's seed and the batch's index (:func:`batch_seed`), and an
episode still running when the batch is full is cut there (its last step bootstraps from the critic, like a time
limit). So a batch depends only on the weights and the random-number state at its start, and a run resumes
exactly (``resume=True``) from its training state, written atomically every ``checkpoint_every`` batches (and
after the batch in which SIGTERM arrived, :func:`~spoil_torchrl.trainers.stop_on_signals`)
(:data:`~spoil_torchrl.runs.directory.CHECKPOINT_NAME`): a resumed run's policies equal an uninterrupted
run's. The policy checkpoints ``ckpt_<frames>.pt`` (actor weights plus the batch's mean episode return and cost)
are written at the same batches, so the four policy types of the paper can be picked from them afterwards.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torch import nn
from torchrl.envs import ExplorationType, TransformedEnv, set_exploration_type
from tqdm.auto import tqdm

from spoil_torchrl.experts.lockstep import LockstepCollector
from spoil_torchrl.experts.ppo_config import PPOConfig
from spoil_torchrl.experts.ppo_update import PPOLearner, ppo_update
from spoil_torchrl.experts.replay import ReplayRecorder
from spoil_torchrl.files import write_atomic
from spoil_torchrl.runs.checkpoint import load_checkpoint, save_checkpoint
from spoil_torchrl.runs.directory import CHECKPOINT_NAME
from spoil_torchrl.runs.results import write_json
from spoil_torchrl.runs.resume import check_resumable
from spoil_torchrl.stack import current_stack
from spoil_torchrl.stopping import raise_if_stopped, stop_requested
from spoil_torchrl.tasks import get_env_task


def batch_seed(seed: int, batch: int) -> int:
    """The environment seed of batch ``batch`` of a run with seed ``seed`` (distinct for distinct pairs).

    Examples:
        >>> batch_seed(0, 0) != batch_seed(0, 1) != batch_seed(1, 0)
        True
    """
    return int(np.random.SeedSequence([seed, batch]).generate_state(1)[0])


class EpisodeTracker:
    """Undiscounted return and cost of the episodes that finish in successive batches of one environment."""

    def __init__(self) -> None:
        self.running = torch.zeros(2, dtype=torch.float64)

    def update(self, batch: TensorDict) -> tuple[float, float, int]:
        """Mean return and cost of the episodes finished in ``batch`` (NaN if none) and their number; a
        ``[num_envs, T]`` batch of environments that each start it afresh counts every row's episodes."""
        if batch.ndim == 2:
            rows = [EpisodeTracker()._finished(row) for row in batch.unbind(0)]
            totals = [t for row in rows for t in row]
            if not totals:
                return math.nan, math.nan, 0
            stacked = torch.stack(totals)
            return float(stacked[:, 0].mean()), float(stacked[:, 1].mean()), len(totals)
        if batch.ndim != 1:
            raise ValueError(
                f"EpisodeTracker expects one environment's [T] batch, got batch size {batch.shape}"
            )
        finished = self._finished(batch)
        if not finished:
            return math.nan, math.nan, 0
        totals = torch.stack(finished)
        return float(totals[:, 0].mean()), float(totals[:, 1].mean()), len(finished)

    def _finished(self, batch: TensorDict) -> list[torch.Tensor]:
        """The (return, cost) of each episode that ends in the [T] ``batch``; the rest runs on."""
        steps = torch.cat([batch["next", "reward"], batch["next", "cost"]], -1).reshape(-1, 2).double()
        done = batch["next", "done"].reshape(-1)
        finished = []
        start = 0
        for end in (done.nonzero().squeeze(-1) + 1).tolist():
            finished.append(self.running + steps[start:end].sum(0))
            self.running = torch.zeros(2, dtype=torch.float64)
            start = end
        self.running = self.running + steps[start:].sum(0)
        return finished


def load_initial_actor(
    learner: PPOLearner, config: PPOConfig, env_id: str | None, observation_dim: int, action_dim: int
) -> None:
    """Copy the weights of the policy ``config.init_actor`` (a file, or ``zoo:<name>`` of ``env_id``) into
    ``learner``'s actor; a policy of another distribution, shape or task, or one that standardises its
    observations (its statistics would not carry over to the training's running ones), is refused."""
    from spoil_torchrl.zoo.policy_files import PolicyFileError, load_policy, policy_path

    source = str(config.init_actor)
    if source.startswith("zoo:") and env_id is None:
        raise ValueError(f"ppo.init_actor = {source!r} needs train_ppo(..., env_id=<the task>)")
    try:
        actor, meta = load_policy(policy_path(source, env_id), env_id=env_id)
    except PolicyFileError as err:
        raise ValueError(f"ppo.init_actor = {source!r}: {err}") from None
    have = (tuple(meta["hidden_cells"]), meta["distribution"], meta["observation_dim"], meta["action_dim"])
    if have != (config.hidden_cells, "tanh_normal", observation_dim, action_dim) or meta["observation_norm"]:
        raise ValueError(
            f"ppo.init_actor = {source!r} is a {meta['distribution']} policy with hidden cells "
            f"{list(meta['hidden_cells'])} for {meta['observation_dim']} -> {meta['action_dim']} dimensions"
            f"{', standardising its observations' if meta['observation_norm'] else ''}; PPO starts from a "
            f"tanh_normal policy with ppo.hidden_cells={list(config.hidden_cells)} for {observation_dim} -> "
            f"{action_dim} dimensions, without observation standardisation of its own"
        )
    learner.actor.load_state_dict(actor.state_dict())


def collect_batch(env: TransformedEnv, actor: nn.Module, config: PPOConfig, index: int) -> TensorDict:
    """Batch ``index``: ``frames_per_batch`` steps of ``actor``'s sampled actions from a reset seeded with
    :func:`batch_seed` (episodes end and reset inside; one still running at the end is cut there)."""
    env.set_seed(batch_seed(config.seed, index))
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        return env.rollout(config.frames_per_batch, actor, break_when_any_done=False, tensordict=env.reset())


def resumable_state(run_dir: str | Path, config: PPOConfig) -> dict:
    """The training state of ``run_dir``, refused
    (:class:`~spoil_torchrl.runs.checkpoint.CheckpointError`) unless it was made with ``config`` on this
    software stack (:func:`~spoil_torchrl.runs.resume.check_resumable`, as for the main recipe's runs):
    what ``resume=true`` continues from. The expert recipe calls it inside its claim of the run directory, so a
    refused resume writes nothing there."""
    run_dir = Path(run_dir)
    state = load_checkpoint(run_dir / CHECKPOINT_NAME)
    as_yaml = lambda settings: OmegaConf.to_yaml({"ppo": json.loads(json.dumps(settings))})  # noqa: E731
    # a setting added since the run was made had its default then (e.g. num_envs: 1)
    settings = {
        **{k: v for k, v in asdict(PPOConfig()).items() if k not in state["config"]},
        **state["config"],
    }
    recorded = {"config_yaml": as_yaml(settings), "results": {"stack": state["stack"]}}
    check_resumable(recorded, as_yaml(asdict(config)), run_dir, settings_file="config.json")
    return state


def train_ppo(
    make_env: Callable[[], TransformedEnv],
    observation_dim: int,
    action_dim: int,
    config: PPOConfig,
    out_dir: str | Path,
    *,
    progress: bool = True,
    resume: bool = False,
    env_id: str | None = None,
) -> list[dict]:
    """Train a PPO (or PPO-Lagrangian, ``config.lagrangian``) policy and checkpoint it under ``out_dir``.

    Args:
        make_env: builds the TorchRL environment (with ``("next", "cost")``), e.g.
            ``functools.partial(spoil_torchrl.envs.make_env, "SafetyPointCircle1-v0")``.
        observation_dim, action_dim: sizes of the task.
        config: :class:`PPOConfig`.
        out_dir: the run directory: ``ckpt_<frames>.pt`` (the actor ``state_dict`` that collected that batch,
            with the batch's episode statistics; loadable with ``weights_only=True``), ``log.jsonl`` (one line
            per batch: frames, mean episode return and cost, lambda, seconds), ``config.json``,
            ``results.json`` (``status``: training, finished, interrupted or failed), the training state
            (:data:`~spoil_torchrl.runs.directory.CHECKPOINT_NAME`) and, with ``record_episodes``, ``replay/``.
        progress: a progress bar over all frames of the run (a resumed run starts it where it stopped), with
            its ETA.
        resume: continue from the training state in ``out_dir`` (same ``config``, same software stack).
        env_id: the task, for ``config.num_envs`` > 1 (the lockstep collector makes its own environments).

    Returns:
        the log lines of the whole run.

    Examples:
        >>> import functools, tempfile
        >>> from spoil_torchrl.envs import make_env
        >>> config = PPOConfig(total_frames=200, frames_per_batch=100, epochs=1, minibatch_size=50,
        ...                    hidden_cells=(8,), checkpoint_every=1)
        >>> log = train_ppo(functools.partial(make_env, "SafetyPointCircle1-v0"), 28, 2, config,
        ...                 tempfile.mkdtemp(), progress=False)
        >>> [line["frames"] for line in log]
        [100, 200]
    """
    check_collector(config, env_id)  # refused before anything is written
    torch.manual_seed(config.seed)
    run_dir = Path(out_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    learner = PPOLearner(observation_dim, action_dim, config)
    log, results = _start(run_dir, learner, config, resume, env_id, observation_dim, action_dim)
    first = len(log)
    recorder = ReplayRecorder(run_dir / "replay", config.record_episodes) if config.record_episodes else None
    batches = math.ceil(config.total_frames / config.frames_per_batch)
    frames = first * config.frames_per_batch
    elapsed = log[-1]["seconds"] if log else 0.0
    bar = tqdm(
        total=batches * config.frames_per_batch,
        initial=frames,
        desc="ppo-lag" if config.lagrangian else "ppo-penalty" if config.cost_penalty else "ppo",
        unit="frame",
        disable=not progress,
    )
    env = (
        make_env()
        if config.num_envs == 1
        else LockstepCollector(
            env_id, config.num_envs, cost_component=config.cost_component, track_ellipse=config.track_ellipse
        )
    )
    start = time.perf_counter()
    try:
        for index in range(first, batches):
            if config.num_envs == 1:
                batch = collect_batch(env, learner.actor, config, index)
            else:
                batch = env.batch(learner.actor, config.frames_per_batch, batch_seed(config.seed, index))
            frames += batch.numel()
            ep_return, ep_cost, n_episodes = EpisodeTracker().update(batch)
            line = {
                "frames": frames,
                "episode_return": ep_return,
                "episode_cost": ep_cost,
                "episodes": n_episodes,
            }
            saving = (index + 1) % config.checkpoint_every == 0 or index + 1 == batches
            if saving:
                save_policy(run_dir, learner, line)
            if recorder is not None:
                recorder.record(batch, index)
            epochs = ppo_update(learner, batch, config, index, ep_cost, batches=batches)
            learner.observe(batch["observation"])  # the next batch's standardisation
            line.update(
                lagrange=float(learner.lagrange.detach()), seconds=elapsed + time.perf_counter() - start
            )
            if config.target_kl is not None:  # how many of its epochs the batch ran before the KL stop
                line["epochs"] = epochs
            log.append(line)
            with open(run_dir / "log.jsonl", "a") as f:
                f.write(json.dumps(line) + "\n")
            results.update(frames=frames, last=line)
            if saving or stop_requested() is not None:  # SIGTERM: keep this batch, then stop
                _save_training_state(run_dir, learner, config, log, results)
            bar.update(batch.numel())
            bar.set_postfix(ret=f"{ep_return:.1f}", cost=f"{ep_cost:.1f}", lam=f"{line['lagrange']:.2f}")
            raise_if_stopped()
    except KeyboardInterrupt:
        write_json(run_dir / "results.json", dict(results, status="interrupted"))
        raise
    except BaseException as err:
        write_json(
            run_dir / "results.json", dict(results, status="failed", error=f"{type(err).__name__}: {err}")
        )
        raise
    finally:
        bar.close()
        env.close()
    write_json(run_dir / "results.json", dict(results, status="finished"))
    return log


def check_collector(config: PPOConfig, env_id: str | None) -> None:
    """Refuse lockstep collection (``config.num_envs`` > 1) without a task, or with fewer steps per environment
    and batch than one episode of it (no episode would finish, so the multiplier would see no cost)."""
    if config.num_envs == 1:
        return
    if env_id is None:
        raise ValueError("ppo.num_envs > 1 needs train_ppo(..., env_id=<the task>)")
    length = get_env_task(env_id).episode_length
    if config.frames_per_batch // config.num_envs < length:
        raise ValueError(
            f"ppo.frames_per_batch / ppo.num_envs = {config.frames_per_batch // config.num_envs} steps per "
            f"environment and batch, fewer than one {env_id} episode ({length} steps): no episode would "
            "ever finish (no cost estimate for the multiplier); raise frames_per_batch or lower num_envs"
        )


def _start(
    run_dir: Path,
    learner: PPOLearner,
    config: PPOConfig,
    resume: bool,
    env_id: str | None,
    observation_dim: int,
    action_dim: int,
) -> tuple[list[dict], dict]:
    """Set ``learner`` and the random state where the run starts (its training state when resuming, else the
    initial actor if any), write ``config.json``, ``log.jsonl`` and ``results.json`` for that start, and return
    the log so far (one line per batch done) and the results being built."""
    state = resumable_state(run_dir, config) if resume else None
    if state is not None:
        learner.load_training_state(state["learner"])
        torch.set_rng_state(state["rng"])
    elif config.init_actor is not None:
        load_initial_actor(learner, config, env_id, observation_dim, action_dim)
    log: list[dict] = [] if state is None else list(state["log"])
    results = {"status": "training", "config": asdict(config), "stack": current_stack(), "frames": 0}
    if state is None:
        write_atomic(run_dir / "config.json", json.dumps(asdict(config), indent=2))
    else:
        results.update(state["results"], status="training")
        results.setdefault("resumed_at", []).append(int(state["frames"]))
    # the log holds every batch once: what a killed run logged after its training state is dropped
    write_atomic(run_dir / "log.jsonl", "".join(json.dumps(line) + "\n" for line in log))
    write_json(run_dir / "results.json", results)
    return log, results


def save_policy(run_dir: Path, learner: PPOLearner, line: dict) -> None:
    """``ckpt_<frames>.pt``: the weights that collected the batch of the log line ``line``, with that batch's
    episode statistics (what the four policy types of the paper are picked from)."""
    torch.save(
        {"actor": learner.actor.state_dict(), "observation_norm": learner.norm is not None, **line},
        run_dir / f"ckpt_{line['frames']:09d}.pt",
    )


def _save_training_state(
    run_dir: Path, learner: PPOLearner, config: PPOConfig, log: list[dict], results: dict
) -> None:
    """The training state a resumed run continues from (atomic, checksummed), then ``results.json``."""
    save_checkpoint(
        run_dir / CHECKPOINT_NAME,
        {
            "config": json.loads(json.dumps(asdict(config))),
            "stack": current_stack(),
            "batches": len(log),
            "frames": results["frames"],
            "learner": learner.training_state(),
            "rng": torch.get_rng_state(),
            "log": log,
            "results": results,
        },
    )
    write_json(run_dir / "results.json", results)
