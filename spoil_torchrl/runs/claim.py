"""Claiming a run of the main recipe: check its settings, then hold its run directory (and, for ``seeds=[...]``,
each seed's folder) under a lock until the run ends (:func:`claim_runs`). A start never overwrites a run, a
refused resume writes nothing, and ``resume=auto`` passes over finished runs. The claim says what each seed
continues from (:class:`Claim`); :func:`~spoil_torchrl.runs.lifecycle.open_runs` takes it from there.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import DictConfig, OmegaConf, open_dict

from spoil_torchrl.algorithms import ALGORITHMS
from spoil_torchrl.runs.checkpoint import load_checkpoint
from spoil_torchrl.runs.directory import (
    CHECKPOINT_NAME,
    LOCK_NAME,
    claim_run_dir,
    release_run_dir,
    write_hydra_record,
)
from spoil_torchrl.runs.pretraining import PRETRAINING_NAME, StoredPretrainingRefused, load_pretraining
from spoil_torchrl.runs.results import settings_yaml
from spoil_torchrl.runs.resume import check_resumable, finished_already
from spoil_torchrl.runs.seed_run import common_checkpoints
from spoil_torchrl.runs.settings import SettingsError, check_settings
from spoil_torchrl.runs.tracking import check_logger_available


@dataclass
class Claim:
    """The run directories a process holds, and what each seed continues from.

    Attributes:
        finished: ``resume=auto`` found every seed finished with these settings; nothing was claimed.
        seeds: per seed, its settings (``seed=<k>``), its run directory and the checkpoint it continues from
            (``None``: it starts), the arguments of :func:`open_run` before ``start``.
        vectorised: a ``seeds=[...]`` run (its main stages train at once, ``train(..., vectorised=True)``).
        start: when the run started (``time.perf_counter``).
    """

    finished: bool
    seeds: list[tuple[DictConfig, Path, Path | None]] = field(default_factory=list)
    vectorised: bool = False
    start: float = 0.0


def seed_settings(cfg: DictConfig, seed: int) -> DictConfig:
    """The settings of seed ``seed`` of a ``seeds=[...]`` run: the single-seed run's (``seed=<seed>``)."""
    seed_cfg = cfg.copy()
    with open_dict(seed_cfg):
        seed_cfg.seed, seed_cfg.seeds = int(seed), None
    return seed_cfg


@contextlib.contextmanager
def claim_runs(cfg: DictConfig, run_dir: Path) -> Iterator[Claim]:
    """Check the settings, then hold ``run_dir`` (and, for ``seeds=[...]``, each ``run_dir/seed<k>``) until the
    block ends. A start never overwrites a run; ``resume=true`` continues the one there after checking that its
    settings are the same (a refused resume writes nothing); ``resume=auto`` passes over finished runs.

    Raises:
        SettingsError: a setting has a value it cannot have, or ``algo.name`` has no builder.
        RunDirError: another process holds the directory, or it holds a run that cannot be continued.
    """
    start = time.perf_counter()
    _check_before_claiming(cfg)
    seeds = [int(s) for s in cfg.get("seeds") or []]
    resume = cfg.get("resume", False)
    if _all_finished(cfg, run_dir, seeds, resume):  # said on the console only: the files stay as they are
        print(f"{run_dir}: finished already; nothing to do (resume=auto)")
        yield Claim(finished=True, start=start)
        return
    stale_lock = _file_state(run_dir / LOCK_NAME)  # a killed run's lock, put back if the resume is refused
    resuming = claim_run_dir(
        run_dir,
        resume="auto" if seeds and resume else resume,
        check=_same_settings_check(cfg, run_dir, seeds),
    )
    if not resuming and not (
        seeds and (run_dir / ".hydra").is_dir()
    ):  # the record of the command that started it
        write_hydra_record(run_dir, cfg)
    claimed = {}  # the seeds' folders held so far (released at the end), with their locks from before
    try:
        if not seeds:
            checkpoint = run_dir / CHECKPOINT_NAME if resuming else None
            yield Claim(finished=False, seeds=[(cfg, run_dir, checkpoint)], start=start)
        else:
            yield _claim_seeds(cfg, run_dir, seeds, claimed, start)
    except StoredPretrainingRefused:  # refused before the run wrote anything: leave the directory as it was
        for folder, lock in [*claimed.items(), (run_dir, stale_lock)]:
            release_run_dir(folder)
            _restore_file(folder / LOCK_NAME, lock)
        raise
    finally:
        for seed_dir in claimed:
            release_run_dir(seed_dir)
        release_run_dir(run_dir)


def _check_before_claiming(cfg: DictConfig) -> None:
    """What can be refused before any data is loaded or anything trained: the settings, the logger's package
    (a missing tensorboard / wandb fails now, not after pre-training) and the algorithm's name."""
    check_settings(OmegaConf.to_container(cfg, resolve=True))
    check_logger_available(cfg.logger.type)
    if cfg.algo.name not in ALGORITHMS:
        raise SettingsError(f"algo.name={cfg.algo.name!r} has no builder; available: {', '.join(ALGORITHMS)}")


def _all_finished(cfg: DictConfig, run_dir: Path, seeds: list[int], resume) -> bool:
    """``resume=auto`` passes over runs that have finished with these settings (a sweep's finished cells)."""
    return all(
        finished_already(
            run_dir / f"seed{s}" if seeds else run_dir, settings_yaml(seed_settings(cfg, s)), resume
        )
        for s in (seeds or [cfg.seed])
    )


def _same_settings_check(cfg: DictConfig, run_dir: Path, seeds: list[int]):
    """The claim check of a single-seed run: a resume's checkpoint and stored pre-training must be readable
    and of these settings (a refused resume writes nothing into the run directory)."""

    def check(resuming: bool) -> None:
        if resuming and not seeds:
            check_resumable(load_checkpoint(run_dir / CHECKPOINT_NAME), settings_yaml(cfg), run_dir)
            if (run_dir / PRETRAINING_NAME).is_file():  # readable, of this algorithm and these settings
                load_pretraining(run_dir, settings_yaml(cfg), algo=cfg.algo.name)

    return check


def _claim_seeds(cfg: DictConfig, run_dir: Path, seeds: list[int], claimed: dict, start: float) -> Claim:
    """A ``seeds=[...]`` run keeps each seed's run in ``seed<k>/``, each claimed on its own (added to
    ``claimed`` as it is held, with its lock from before); every seed continues from the last step they all have
    a checkpoint of."""
    settings = run_dir / "config.yaml"
    if not settings.is_file() or settings.read_text() != settings_yaml(cfg):  # a resume's are the same
        settings.write_text(settings_yaml(cfg))
    resuming = []
    for seed in seeds:
        seed_dir = run_dir / f"seed{seed}"
        stale_lock = _file_state(seed_dir / LOCK_NAME)
        stored = _stored_pretraining_check(seed_dir, seed_settings(cfg, seed))
        resuming.append(claim_run_dir(seed_dir, resume=cfg.get("resume", False), check=stored))
        claimed[seed_dir] = stale_lock
    checkpoints = common_checkpoints(list(claimed), resuming)
    return Claim(
        finished=False,
        seeds=[
            (seed_settings(cfg, seed), seed_dir, checkpoint)
            for seed, seed_dir, checkpoint in zip(seeds, claimed, checkpoints, strict=True)
        ],
        vectorised=True,
        start=start,
    )


def _stored_pretraining_check(run_dir: Path, cfg: DictConfig):
    """The claim check of a seed's folder: a resumed seed's stored pre-training must be readable and its own."""

    def check(resuming: bool) -> None:
        if resuming and (run_dir / PRETRAINING_NAME).is_file():
            load_pretraining(run_dir, settings_yaml(cfg), algo=cfg.algo.name)

    return check


def _file_state(path: Path) -> tuple[bytes, int] | None:
    """A file's bytes and modification time (``None`` when there is none)."""
    return (path.read_bytes(), path.stat().st_mtime_ns) if path.is_file() else None


def _restore_file(path: Path, state: tuple[bytes, int] | None) -> None:
    """Put back what :func:`_file_state` read (nothing, if there was no file)."""
    if state is not None:
        path.write_bytes(state[0])
        os.utime(path, ns=(state[1], state[1]))
