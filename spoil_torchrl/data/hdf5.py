"""Read and write DSRL-layout HDF5 files (flat root datasets, episodes back to back)."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path

import h5py
import numpy as np
import torch
from tensordict import MemoryMappedTensor, TensorDict

from spoil_torchrl.data.episodes import DSRL_KEYS, DatasetError, episodes_from_arrays

#: HDF5 attribute holding the JSON metadata of files written by this project.
METADATA_ATTR = "spoil_torchrl_metadata"
FLOAT_KEYS = ("observations", "next_observations", "actions", "rewards", "costs")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _open(path: Path) -> h5py.File:
    if not path.exists():
        raise DatasetError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise DatasetError(f"{path}: the file is empty (0 bytes); delete it and fetch it again")
    if not h5py.is_hdf5(path):
        raise DatasetError(f"{path}: not an HDF5 file (a partial download? delete it and fetch it again)")
    try:
        return h5py.File(path, "r")
    except OSError as err:
        raise DatasetError(
            f"{path}: the HDF5 file is truncated or corrupt ({err}); delete it and fetch it again"
        ) from err


def _read(dset: h5py.Dataset, path: Path, key: str, memmap_dir: Path | None) -> np.ndarray | torch.Tensor:
    """Read one dataset into a fresh array (one copy: HDF5 -> memory), float data as float32."""
    dtype = np.float32 if key in FLOAT_KEYS else dset.dtype
    try:
        if memmap_dir is not None:
            out = MemoryMappedTensor.empty(
                dset.shape,
                dtype=torch.from_numpy(np.empty(0, dtype)).dtype,
                filename=memmap_dir / f"{key}.memmap",
            )
            target = out.numpy()
        else:
            out = target = np.empty(dset.shape, dtype=dtype)
        if dset.size:
            dset.read_direct(target)  # HDF5 converts the type while reading: no intermediate copy
        return out
    except (OSError, ValueError, TypeError) as err:
        raise DatasetError(
            f"{path}: cannot read '{key}' ({err}); the file may be truncated or corrupt"
        ) from err


def read_dsrl_file(
    path: str | os.PathLike,
    *,
    observation_dim: int | None = None,
    action_dim: int | None = None,
    memmap_dir: str | os.PathLike | None = None,
) -> TensorDict:
    """Load a DSRL-layout HDF5 file as TED-layout transitions (see :func:`episodes_from_arrays`).

    Each array is read once, straight into its final buffer (float data as float32). With ``memmap_dir`` the
    buffers are memory-mapped files there instead of RAM, for datasets larger than memory. Every problem with
    the file is a :class:`~spoil_torchrl.data.DatasetError` naming it: missing file, empty file, not HDF5,
    truncated, missing key, ragged arrays, NaN / inf, wrong dimensions.
    """
    path = Path(path)
    mm = None if memmap_dir is None else Path(memmap_dir)
    if mm is not None:
        mm.mkdir(parents=True, exist_ok=True)
    with _open(path) as f:
        missing = [k for k in DSRL_KEYS if k not in f]
        if missing:
            raise DatasetError(
                f"{path}: missing array '{missing[0]}' (a DSRL file has {', '.join(DSRL_KEYS)})"
            )
        arrays = {k: _read(f[k], path, k, mm) for k in DSRL_KEYS}
    return episodes_from_arrays(
        arrays, source=str(path), observation_dim=observation_dim, action_dim=action_dim
    )


def read_metadata(path: str | os.PathLike) -> dict:
    """The JSON metadata this project writes into its own files (``{}`` for plain DSRL files)."""
    with _open(Path(path)) as f:
        raw = f.attrs.get(METADATA_ATTR)
    return json.loads(raw) if raw is not None else {}


def write_dsrl_file(
    path: str | os.PathLike,
    arrays: Mapping[str, np.ndarray | torch.Tensor],
    *,
    metadata: Mapping | None = None,
    compression: str | None = "gzip",
) -> Path:
    """Write ``arrays`` (the DSRL keys) to ``path`` atomically: a killed writer leaves no file that loads.

    The data go to a unique ``<path>.<random>.tmp`` first and are renamed into place once complete.
    ``metadata`` is stored as a JSON attribute. Examples are in the tests; the collection pipeline
    (:func:`spoil_torchrl.data.collect.collect`) writes its datasets through here.
    """
    path = Path(path)
    missing = [k for k in DSRL_KEYS if k not in arrays]
    if missing:
        raise DatasetError(f"cannot write {path}: missing array '{missing[0]}'")
    path.parent.mkdir(parents=True, exist_ok=True)
    # a unique temporary name: two writers of the same file never share (or publish) each other's half file
    fd, tmp_name = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes it owner-only; a dataset gets the usual permissions
    try:
        with h5py.File(tmp, "w") as f:
            for key in DSRL_KEYS:
                value = arrays[key]
                value = value.numpy() if isinstance(value, torch.Tensor) else np.asarray(value)
                f.create_dataset(key, data=value, compression=compression)
            if metadata is not None:
                f.attrs[METADATA_ATTR] = json.dumps(dict(metadata))
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
