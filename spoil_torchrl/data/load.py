"""``load_episodes(source)``: one entry point for every dataset the library reads.

Sources:

* ``"file:<path>"`` -- any HDF5 file in the DSRL layout;
* ``"dsrl:<dataset id>"`` -- one of the 38 DSRL datasets (:data:`spoil_torchrl.tasks.DSRL_DATASETS`), found in
  ``$DSRL_DATASET_DIR`` or ``~/.dsrl/datasets`` (the ``dsrl`` package's own cache, so existing downloads are
  reused) and downloaded there otherwise;
* ``"generated:<name>"`` -- datasets made by this project's collection pipeline, in ``$SPOIL_TORCHRL_DATA_DIR``
  or ``~/.cache/spoil_torchrl/generated`` as ``<name>.hdf5`` (same layout plus metadata);
* ``"minari:<dataset id>"`` -- a Minari dataset with per-step costs (:mod:`spoil_torchrl.data.minari_io`), in
  ``$MINARI_DATASETS_PATH`` or ``~/.minari/datasets``, downloaded from Minari's remote otherwise (extra
  ``[minari]``).
"""

from __future__ import annotations

import os
from pathlib import Path

from tensordict import TensorDict

from spoil_torchrl.data.download import download
from spoil_torchrl.data.episodes import DatasetError
from spoil_torchrl.data.generated import generated_path, missing_generated_error
from spoil_torchrl.data.hdf5 import _open, read_dsrl_file, read_metadata
from spoil_torchrl.tasks import DSRLDataset, get_dsrl_dataset

SCHEMES = ("file", "dsrl", "generated", "minari")


def dsrl_cache_dir() -> Path:
    """``$DSRL_DATASET_DIR`` if set, else ``~/.dsrl/datasets`` (where the ``dsrl`` package caches files).

    Examples:
        >>> from unittest import mock
        >>> with mock.patch.dict(os.environ, {"DSRL_DATASET_DIR": "/data/dsrl"}):
        ...     dsrl_cache_dir() / get_dsrl_dataset("OfflineCarCircle-v0").file_name
        PosixPath('/data/dsrl/SafetyCarCircle-v0-100-1450.hdf5')
    """
    return Path(os.environ.get("DSRL_DATASET_DIR", Path.home() / ".dsrl" / "datasets")).expanduser()


def _check_hdf5(path: Path) -> None:
    _open(path).close()


def fetch_dsrl(dataset: DSRLDataset, *, progress: bool = True) -> Path:
    """The local path of a DSRL dataset's file, downloading it into :func:`dsrl_cache_dir` if needed.

    A file already in the cache (e.g. copied there by hand on a machine without network access) is used as it
    is.

    Examples:
        >>> import tempfile
        >>> from unittest import mock
        >>> dataset = get_dsrl_dataset("OfflineCarCircle-v0")
        >>> cache = Path(tempfile.mkdtemp())
        >>> _ = (cache / dataset.file_name).write_bytes(b"")  # stands in for the file placed by hand
        >>> with mock.patch.dict(os.environ, {"DSRL_DATASET_DIR": str(cache)}):
        ...     path = fetch_dsrl(dataset)  # found: nothing is downloaded
        >>> path == cache / "SafetyCarCircle-v0-100-1450.hdf5"
        True
    """
    destination = dsrl_cache_dir() / dataset.file_name
    return download(dataset.url, destination, validate=_check_hdf5, progress=progress)


def parse_source(source: str) -> tuple[str, str]:
    """Split ``"scheme:rest"``; a bare existing path is taken as ``file:``.

    Raises:
        DatasetError: ``source`` has none of the :data:`SCHEMES` and is no existing path (the main recipe
            reports it in one line).

    Examples:
        >>> parse_source("dsrl:OfflineCarCircle-v0")
        ('dsrl', 'OfflineCarCircle-v0')
        >>> parse_source("s3:bucket/file")
        Traceback (most recent call last):
        ...
        spoil_torchrl.data.episodes.DatasetError: dataset.source = 's3:bucket/file': unknown dataset source; \
use one of 'file:...', 'dsrl:...', 'generated:...', 'minari:...' or the path of an existing file
    """
    scheme, sep, rest = source.partition(":")
    if sep and scheme in SCHEMES and rest:
        return scheme, rest
    if Path(source).exists():
        return "file", source
    raise DatasetError(
        f"dataset.source = {source!r}: unknown dataset source; use one of "
        + ", ".join(f"'{s}:...'" for s in SCHEMES)
        + " or the path of an existing file"
    )


def load_episodes(
    source: str, *, memmap_dir: str | os.PathLike | None = None, progress: bool = True
) -> TensorDict:
    """Load a dataset as TED-layout transitions with ``episode`` ids and ``is_init`` flags.

    Args:
        source: ``"file:<path>"``, ``"dsrl:<dataset id>"``, ``"generated:<name>"`` or ``"minari:<dataset id>"``
            (see module docstring).
        memmap_dir: keep the arrays memory-mapped in this folder instead of RAM.
        progress: show a progress bar while downloading.

    For DSRL datasets the observation / action sizes are checked against the task table. Minari datasets are
    read into RAM (``memmap_dir`` does not apply to them).

    Examples:
        >>> import tempfile
        >>> import numpy as np
        >>> from spoil_torchrl.data import DSRL_KEYS, write_dsrl_file
        >>> arrays = {k: np.zeros((6, 3), np.float32) for k in DSRL_KEYS[:3]}  # observations, actions
        >>> arrays |= {k: np.zeros(6, np.float32) for k in DSRL_KEYS[3:]}  # rewards, costs, flags
        >>> arrays["timeouts"][[2, 5]] = 1  # two episodes of three steps
        >>> path = write_dsrl_file(Path(tempfile.mkdtemp()) / "demo.hdf5", arrays)
        >>> episodes = load_episodes(f"file:{path}")
        >>> episodes.batch_size, episodes["episode"].tolist()
        (torch.Size([6]), [0, 0, 0, 1, 1, 1])
        >>> episodes["observation"].dtype, episodes["next", "reward"].shape, episodes["is_init"].sum().item()
        (torch.float32, torch.Size([6, 1]), 2)
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
    if scheme == "minari":
        from spoil_torchrl.data.minari_io import read_minari

        return read_minari(rest)
    path = generated_path(rest)
    if not path.exists():
        raise DatasetError(missing_generated_error(rest))
    return read_dsrl_file(path, memmap_dir=memmap_dir)


def read_source_metadata(source: str) -> dict:
    """The metadata a source carries: this project's JSON metadata of a ``file:`` / ``generated:`` HDF5 file
    (``{}`` for a plain DSRL file), the ``spoil_torchrl`` entry of a ``minari:`` dataset (see
    :func:`~spoil_torchrl.data.minari_io.read_minari_metadata`), ``{}`` for ``dsrl:`` (the task table has its
    constants). The data must have been loaded (or made) first.

    Examples:
        >>> import tempfile
        >>> import numpy as np
        >>> from spoil_torchrl.data import DSRL_KEYS, write_dsrl_file
        >>> arrays = {k: np.zeros((2, 3), np.float32) for k in DSRL_KEYS[:3]}  # observations, actions
        >>> arrays |= {k: np.array([0, 1], np.float32) for k in DSRL_KEYS[3:]}  # one episode of two steps
        >>> path = Path(tempfile.mkdtemp()) / "demo.hdf5"
        >>> path = write_dsrl_file(path, arrays, metadata={"cost_threshold": 25})
        >>> read_source_metadata(f"file:{path}"), read_source_metadata("dsrl:OfflineCarCircle-v0")
        ({'cost_threshold': 25}, {})
    """
    scheme, rest = parse_source(source)
    if scheme == "file":
        return read_metadata(Path(rest).expanduser())
    if scheme == "generated":
        return read_metadata(generated_path(rest))
    if scheme == "minari":
        from spoil_torchrl.data.minari_io import read_minari_metadata

        return read_minari_metadata(rest)
    return {}
