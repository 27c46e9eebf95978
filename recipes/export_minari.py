"""Export a dataset, with the IL-SP roles the main recipe would use, as a local Minari dataset.

    python recipes/export_minari.py                                   # the embedded default, roles of seed 0
    python recipes/export_minari.py dataset=point_circle1_controlled seed=1 dataset_id=me/pc1-controlled-v0

Every episode of ``dataset.source`` is written (observations, actions, rewards, flags, the per-step cost as
``infos["cost"]``), with each episode's ``policy_type`` where the source records it and ``role_safe`` /
``role_performant`` / ``role_unlabeled`` flags: the roles :func:`~spoil_torchrl.data.prepare.prepare_dataset`
draws for ``seed`` with the dataset config's scheme and sizes. The result lands in ``$MINARI_DATASETS_PATH``
(default ``~/.minari/datasets``); others load it with ``minari.load_dataset(id)``, and the main recipe trains
on it with ``dataset.source=minari:<id> dataset.scheme=stored`` (the stored roles) or any other scheme.
"""

from __future__ import annotations

import logging

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from spoil_torchrl.data.minari_export import write_minari
from spoil_torchrl.data.minari_io import minari_dataset_path
from spoil_torchrl.data.prepare import prepare_dataset

log = logging.getLogger(__name__)


@hydra.main(config_path="../configs", config_name="export_minari", version_base="1.3")
def main(cfg: DictConfig) -> None:
    dataset_id = cfg.dataset_id or f"spoil_torchrl/{cfg.dataset.name}-seed{cfg.seed}-v0"
    data = prepare_dataset(
        cfg.dataset,
        env_id=cfg.task.env_id,
        seed=int(cfg.seed),
        progress=cfg.progress,
        extra_roles=tuple(cfg.extra_roles),
    )
    metadata = {
        **data.metadata,
        "env_id": data.env_id,
        "cost_threshold": data.cost_threshold,
        "source": cfg.dataset.source,
        "roles_drawn_with": {"scheme": cfg.dataset.scheme, "seed": int(cfg.seed)},
    }
    dataset = write_minari(
        data.episodes,
        dataset_id,
        metadata=metadata,
        roles=data.roles,
        return_range=data.return_range,
        description=f"{cfg.dataset.source} with the IL-SP roles of seed {cfg.seed} ({cfg.dataset.scheme})",
        overwrite=cfg.overwrite,
    )
    sizes = ", ".join(f"{role} {ids.numel()}" for role, ids in data.roles.items())
    config = HydraConfig.get().runtime.choices.get("dataset")  # its task and constants, for the command below
    log.info(
        f"{dataset_id}: {dataset.total_episodes} episodes, {dataset.total_steps} steps in "
        f"{minari_dataset_path(dataset_id)} (roles: {sizes} episodes)\n"
        f"train on it: python recipes/spoildice_dsrl.py dataset={config} dataset.source=minari:{dataset_id} "
        "dataset.scheme=stored"
    )


if __name__ == "__main__":
    main()
