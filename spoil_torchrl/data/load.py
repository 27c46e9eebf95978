"""``load_episodes(source)``: one entry point for every dataset the library reads.

Sources:

* ``"file:<path>"`` -- any HDF5 file in the DSRL layout;
* ``"dsrl:<dataset id>"`` -- one of the 38 DSRL datasets (:data:`spoil_torchrl.tasks.DSRL_DATASETS`), found in
  ``$DSRL_DATASET_DIR`` or ``~/.dsrl/datasets`` (the ``dsrl`` package's own cache, so existing downloads are
  reused) and downloaded there otherwise;
* ``"generated:<name>"`` -- datasets made by this project's collection pipeline, in ``$SPOIL_TORCHRL_DATA_DIR``
  or ``~/.cache/spoil_torchrl/generated`` as ``<name>.hdf5`` (same layout plus metadata).
"""

from __future__ import annotations

import os
from pathlib import Path

from tensordict import TensorDict

from spoil_torchrl.data.download import download
from spoil_torchrl.data.episodes import DatasetError
from spoil_torchrl.data.hdf5 import _open, read_dsrl_file
from spoil_torchrl.tasks import DSRLDataset, get_dsrl_dataset

SCHEMES = ("file", "dsrl", "generated")


def dsrl_cache_dir() -> Path:
    """``$DSRL_DATASET_DIR`` if set, else ``~/.dsrl/datasets`` (where the ``dsrl`` package caches files)."""
    return Path(os.environ.get("DSRL_DATASET_DIR", Path.home() / ".dsrl" / "datasets")).expanduser()


def generated_data_dir() -> Path:
    """``$SPOIL_TORCHRL_DATA_DIR`` if set, else ``~/.cache/spoil_torchrl/generated``."""
    default = Path.home() / ".cache" / "spoil_torchrl" / "generated"
    return Path(os.environ.get("SPOIL_TORCHRL_DATA_DIR", default)).expanduser()


def _check_hdf5(path: Path) -> None:
    _open(path).close()


def fetch_dsrl(dataset: DSRLDataset, *, progress: bool = True) -> Path:
    """The local path of a DSRL dataset's file, downloading it into :func:`dsrl_cache_dir` if needed."""
    destination = dsrl_cache_dir() / dataset.file_name
    return download(dataset.url, destination, validate=_check_hdf5, progress=progress)


def parse_source(source: str) -> tuple[str, str]:
    """Split ``"scheme:rest"``; a bare existing path is taken as ``file:``.

    Examples:
        >>> parse_source("dsrl:OfflineCarCircle-v0")
        ('dsrl', 'OfflineCarCircle-v0')
    """
    scheme, sep, rest = source.partition(":")
    if sep and scheme in SCHEMES and rest:
        return scheme, rest
    if Path(source).exists():
        return "file", source
    raise ValueError(
        f"unknown dataset source {source!r}: use one of " + ", ".join(f"'{s}:...'" for s in SCHEMES)
    )


def load_episodes(
    source: str, *, memmap_dir: str | os.PathLike | None = None, progress: bool = True
) -> TensorDict:
    """Load a dataset as TED-layout transitions with ``episode`` ids and ``is_init`` flags.

    Args:
        source: ``"file:<path>"``, ``"dsrl:<dataset id>"`` or ``"generated:<name>"`` (see module docstring).
        memmap_dir: keep the arrays memory-mapped in this folder instead of RAM.
        progress: show a progress bar while downloading.

    For DSRL datasets the observation / action sizes are checked against the task table.
    """
    scheme, rest = parse_source(source)
    if scheme == "file":
        return read_dsrl_file(Path(rest).expanduser(), memmap_dir=memmap_dir)
    if scheme == "dsrl":
        dataset = get_dsrl_dataset(rest)
        path = fetch_dsrl(dataset, progress=progress)
        return read_dsrl_file(
            path,
            observation_dim=dataset.observation_dim,
            action_dim=dataset.action_dim,
            memmap_dir=memmap_dir,
        )
    path = generated_data_dir() / f"{rest}.hdf5"
    if not path.exists():
        from spoil_torchrl.data.generated import GENERATED_DATASETS

        if rest in GENERATED_DATASETS:
            how = f"make it with `python recipes/collect_demos.py name={rest}`"
        else:
            how = (
                f"it is not one of the known generated datasets ({', '.join(GENERATED_DATASETS)}); add it to "
                "spoil_torchrl/data/generated.py and make it with recipes/collect_demos.py"
            )
        raise DatasetError(
            f"generated dataset {rest!r} not found at {path}; {how} "
            "(or set SPOIL_TORCHRL_DATA_DIR to where it lives)"
        )
    return read_dsrl_file(path, memmap_dir=memmap_dir)
