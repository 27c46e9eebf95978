"""Datasets: loading (DSRL layout), IL-SP labelling, controlled mixes and dual-demonstration buffers."""

from spoil_torchrl.data.buffers import DualDemoBuffers
from spoil_torchrl.data.collect import Segment, collect, segment_pools
from spoil_torchrl.data.download import download, sha256_of
from spoil_torchrl.data.episodes import (
    DSRL_KEYS,
    DatasetError,
    episodes_from_arrays,
    fit_observation_normalizer,
    select_episodes,
    standardize_observations,
    validate_arrays,
)
from spoil_torchrl.data.generated import (
    DEFAULT_DATASET,
    GENERATED_DATASETS,
    ensure_generated,
    generated_data_dir,
    generated_path,
    get_generated,
)
from spoil_torchrl.data.hdf5 import read_dsrl_file, read_metadata, write_dsrl_file
from spoil_torchrl.data.labeling import (
    POOLS,
    controlled_mix,
    corrupt,
    draw,
    episode_stats,
    ilsp_return_threshold,
    label_ilsp,
    replay_subsets,
    stats_table,
)
from spoil_torchrl.data.load import (
    dsrl_cache_dir,
    fetch_dsrl,
    load_episodes,
    parse_source,
    read_source_metadata,
)

__all__ = [
    "DEFAULT_DATASET",
    "DSRL_KEYS",
    "GENERATED_DATASETS",
    "Segment",
    "collect",
    "ensure_generated",
    "generated_path",
    "get_generated",
    "segment_pools",
    "POOLS",
    "DatasetError",
    "DualDemoBuffers",
    "controlled_mix",
    "corrupt",
    "download",
    "draw",
    "dsrl_cache_dir",
    "episode_stats",
    "episodes_from_arrays",
    "fetch_dsrl",
    "fit_observation_normalizer",
    "generated_data_dir",
    "ilsp_return_threshold",
    "label_ilsp",
    "load_episodes",
    "parse_source",
    "read_dsrl_file",
    "read_metadata",
    "read_source_metadata",
    "replay_subsets",
    "select_episodes",
    "sha256_of",
    "standardize_observations",
    "stats_table",
    "validate_arrays",
    "write_dsrl_file",
]
