"""Make a named demonstration dataset from the committed expert policies (paper appendix F.2).

    python recipes/collect_demos.py                                     # the main recipe's embedded default
    python recipes/collect_demos.py name=point-circle1-controlled    # the four typed pools, 500 each

The file lands in ``$SPOIL_TORCHRL_DATA_DIR`` (default ``~/.cache/spoil_torchrl/generated``) as
``<dataset>.hdf5`` and loads with ``load_episodes("generated:<dataset>")``. A cached file is reused unless
``force=true``. At the end a Table-I-style summary (return, feasible return, cost per policy label) is printed.
"""

from __future__ import annotations

import logging
import sys
import time

import hydra
import torch
from omegaconf import DictConfig

from spoil_torchrl.data import ensure_generated, get_generated, load_episodes, read_metadata, segment_pools
from spoil_torchrl.eval import policy_table
from spoil_torchrl.tasks import UnknownDatasetError
from spoil_torchrl.trainers.settings import SettingsError, check_settings

log = logging.getLogger(__name__)


@hydra.main(config_path="../configs", config_name="collect_demos", version_base="1.3")
def main(cfg: DictConfig) -> None:
    try:
        check_settings({"threads": cfg.threads, "progress": cfg.progress, "force": cfg.force})
        if not (isinstance(cfg.num_envs, int) and cfg.num_envs >= 1):
            raise SettingsError(f"num_envs = {cfg.num_envs!r}: expected an integer >= 1")
        spec = get_generated(cfg.name)
    except (SettingsError, UnknownDatasetError) as err:
        sys.exit(f"error: {err}")
    torch.set_num_threads(cfg.threads)
    start = time.perf_counter()
    path = ensure_generated(cfg.name, force=cfg.force, num_envs=cfg.num_envs, progress=cfg.progress)
    meta = read_metadata(path)
    episodes = load_episodes(f"generated:{cfg.name}")
    log.info(
        f"{cfg.name}: {spec.episodes} episodes of {spec.env_id}, {meta['steps']} steps, in {path}\n"
        f"(made in {meta['seconds']:.0f} s = {meta['steps'] / meta['seconds']:.0f} steps/s; this call "
        f"{time.perf_counter() - start:.0f} s); random-policy return {meta['random_return']}, "
        f"safe-high return {meta['safe_high_return']}\n"
    )
    log.info(policy_table(episodes, segment_pools(meta), cost_threshold=meta["cost_threshold"]))


if __name__ == "__main__":
    main()
