"""Read and write DSRL-layout HDF5 files (flat root datasets, episodes back to back)."""

from __future__ import annotations

import errno
import json
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path

import h5py
import numpy as np
import torch
from tensordict import MemoryMappedTensor, TensorDict

from spoil_torchrl.data.episodes import (
    DSRL_KEYS,
    DatasetError,
    _first_non_finite_row,
    episodes_from_arrays,
)
from spoil_torchrl.envs.cost_components import COMPONENT_PREFIX

#: HDF5 attribute holding the JSON metadata of files written by this project.
METADATA_ATTR = "spoil_torchrl_metadata"
FLOAT_KEYS = ("observations", "next_observations", "actions", "rewards", "costs")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _open(path: Path) -> h5py.File:
    if path.is_symlink():
        try:
            path.resolve(strict=True)
        except (RuntimeError, OSError) as err:  # Python < 3.13 raises RuntimeError for a loop
            if isinstance(err, RuntimeError) or err.errno == errno.ELOOP:
                raise DatasetError(
                    f"{path}: a symlink loop (the link leads back to itself); fix the link"
                ) from None
            raise DatasetError(f"{path}: a broken symlink (to {os.readlink(path)})") from None
    if not path.exists():
        raise DatasetError(f"{path}: no such file")
    if path.is_dir():
        raise DatasetError(f"{path}: a directory, not an HDF5 file; give the file inside it")
    if path.stat().st_size == 0:
        raise DatasetError(f"{path}: the file is empty (0 bytes); delete it and fetch it again")
    if not h5py.is_hdf5(path):
        raise DatasetError(f"{path}: not an HDF5 file (a partial download? delete it and fetch it again)")
    try:
        return h5py.File(path, "r")
    except (OSError, RuntimeError) as err:  # h5py raises RuntimeError for some damaged headers
        if getattr(err, "errno", None) in (errno.EAGAIN, errno.EACCES) and "lock" in str(err):
            raise DatasetError(
                f"{path}: another process has this file open for writing (HDF5 file locking); wait for it to "
                "finish, then run again (the file is not damaged: keep it)"
            ) from None
        raise DatasetError(
            f"{path}: the HDF5 file is truncated or corrupt ({err}); delete it and fetch it again"
        ) from err


def _refuse_float32_overflow(dset: h5py.Dataset, target: np.ndarray, path: Path, key: str) -> None:
    """A float64 value beyond float32's range became infinite when read as float32: say so (the file itself
    holds no infinity). The first non-finite row is found as the arrays' own check finds it."""
    row = _first_non_finite_row(torch.from_numpy(target))
    if row < 0:
        return
    original = np.asarray(dset[row], dtype=np.float64)
    if np.isfinite(original).all():  # else the file holds NaN / inf itself, which validation reports
        value = original.reshape(-1)[~np.isfinite(np.asarray(target[row]).reshape(-1))][0]
        raise DatasetError(
            f"{path}: '{key}' holds {value:.3g} at row {row}, beyond the float32 range (±3.4e38) in "
            "which the data are trained on; rescale that column"
        )


def _read(dset: h5py.Dataset, path: Path, key: str, memmap_dir: Path | None) -> np.ndarray | torch.Tensor:
    """Read one dataset into a fresh array (one copy: HDF5 -> memory), float data as float32."""
    dtype = np.float32 if key in FLOAT_KEYS or key.startswith(COMPONENT_PREFIX) else dset.dtype
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
    except (OSError, ValueError, TypeError) as err:
        raise DatasetError(
            f"{path}: cannot read '{key}' ({err}); the file may be truncated or corrupt"
        ) from err
    if dset.size and dtype == np.float32 and dset.dtype.kind == "f" and dset.dtype.itemsize > 4:
        _refuse_float32_overflow(dset, target, path, key)
    return out


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

    Examples:
        >>> arrays = {k: np.zeros((5, 3), np.float32) for k in DSRL_KEYS[:3]}  # observations, actions
        >>> arrays |= {k: np.zeros(5, np.float32) for k in DSRL_KEYS[3:]}  # rewards, costs, flags
        >>> arrays["terminals"][1] = arrays["timeouts"][4] = 1  # a terminal episode, then a cut one
        >>> path = write_dsrl_file(Path(tempfile.mkdtemp()) / "demo.hdf5", arrays)
        >>> td = read_dsrl_file(path, observation_dim=3, action_dim=3)
        >>> td.batch_size, td["episode"].tolist(), td["next", "terminated"].squeeze(-1).tolist()
        (torch.Size([5]), [0, 0, 1, 1, 1], [False, True, False, False, False])
        >>> read_dsrl_file(path, observation_dim=28)
        Traceback (most recent call last):
        ...
        spoil_torchrl.data.episodes.DatasetError: .../demo.hdf5: observation dimension is 3, but the task \
expects 28
    """
    path = Path(path)
    mm = None if memmap_dir is None else Path(memmap_dir)
    if mm is not None:
        mm.mkdir(parents=True, exist_ok=True)
    with _open(path) as f:
        try:
            missing = [k for k in DSRL_KEYS if k not in f]
            if missing:
                raise DatasetError(
                    f"{path}: missing array '{missing[0]}' (a DSRL file has {', '.join(DSRL_KEYS)})"
                )
            # the DSRL arrays and the constraints' own costs (cost_<name>, data/constraint_costs.py)
            objects = {k: f[k] for k in (*DSRL_KEYS, *sorted(k for k in f if k.startswith(COMPONENT_PREFIX)))}
            odd = [k for k, v in objects.items() if not isinstance(v, h5py.Dataset)]
            if odd:
                raise DatasetError(f"{path}: '{odd[0]}' is a {type(objects[odd[0]]).__name__}, not an array")
            arrays = {k: _read(v, path, k, mm) for k, v in objects.items()}
            costs = objects["costs"]  # a [N, K] array's columns are named by the metadata
            constraints = (
                _metadata(f, path).get("constraints") if costs.ndim == 2 and costs.shape[1] > 1 else None
            )
        except DatasetError:  # already names the file and the problem
            raise
        except (OSError, RuntimeError, KeyError, ValueError, TypeError) as err:  # a damaged header or link
            raise DatasetError(f"{path}: the HDF5 file is corrupt ({type(err).__name__}: {err})") from err
    return episodes_from_arrays(
        arrays,
        source=str(path),
        observation_dim=observation_dim,
        action_dim=action_dim,
        constraints=constraints,
    )


def read_metadata(path: str | os.PathLike) -> dict:
    """The JSON metadata this project writes into its own files (``{}`` for plain DSRL files).

    Examples:
        >>> arrays = {k: np.zeros((2, 3), np.float32) for k in DSRL_KEYS[:3]}  # observations, actions
        >>> arrays |= {k: np.array([0, 1], np.float32) for k in DSRL_KEYS[3:]}  # one episode of two steps
        >>> folder = Path(tempfile.mkdtemp())
        >>> ours = write_dsrl_file(folder / "ours.hdf5", arrays, metadata={"env_id": "SafetyPointCircle1-v0"})
        >>> plain = write_dsrl_file(folder / "plain.hdf5", arrays)  # as a DSRL download: no metadata
        >>> read_metadata(ours), read_metadata(plain)
        ({'env_id': 'SafetyPointCircle1-v0'}, {})
    """
    path = Path(path)
    with _open(path) as f:
        return _metadata(f, path)


def _metadata(f: h5py.File, path: Path) -> dict:
    """:func:`read_metadata` of an open file."""
    try:
        raw = f.attrs.get(METADATA_ATTR)
    except (OSError, RuntimeError, KeyError) as err:
        raise DatasetError(f"{path}: cannot read the metadata attribute ({err})") from err
    if raw is None:
        return {}
    try:
        metadata = json.loads(raw)
    except (ValueError, TypeError) as err:
        raise DatasetError(
            f"{path}: the metadata attribute {METADATA_ATTR!r} is not valid JSON ({err})"
        ) from None
    if not isinstance(metadata, dict):
        raise DatasetError(f"{path}: the metadata attribute {METADATA_ATTR!r} is not a JSON object")
    return metadata


def write_dsrl_file(
    path: str | os.PathLike,
    arrays: Mapping[str, np.ndarray | torch.Tensor],
    *,
    metadata: Mapping | None = None,
    compression: str | None = "gzip",
) -> Path:
    """Write ``arrays`` (the DSRL keys, and any ``cost_<name>`` arrays of per-constraint costs) to ``path``
    atomically: a killed writer leaves no file that loads.

    The data go to a unique ``<path>.<random>.tmp`` first and are renamed into place once complete.
    ``metadata`` is stored as a JSON attribute. The collection pipeline
    (:func:`spoil_torchrl.data.collect.collect`) writes its datasets through here.

    Examples:
        >>> n = 4  # two episodes of two steps, back to back
        >>> arrays = {"observations": np.zeros((n, 3), np.float32), "next_observations": np.ones((n, 3)),
        ...           "actions": np.zeros((n, 2), np.float32), "rewards": np.ones(n, np.float32),
        ...           "costs": np.zeros(n, np.float32), "terminals": np.zeros(n, bool),
        ...           "timeouts": np.array([0, 1, 0, 1], bool)}
        >>> path = write_dsrl_file(Path(tempfile.mkdtemp()) / "demo.hdf5", arrays, metadata={"seed": 0})
        >>> sorted(p.name for p in path.parent.iterdir())  # no temporary file is left
        ['demo.hdf5']
        >>> read_dsrl_file(path)["episode"].tolist(), read_metadata(path)
        ([0, 0, 1, 1], {'seed': 0})
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
            extra = sorted(k for k in arrays if k.startswith(COMPONENT_PREFIX))  # the constraints' own costs
            for key in (*DSRL_KEYS, *extra):
                value = arrays[key]
                value = value.numpy() if isinstance(value, torch.Tensor) else np.asarray(value)
                # fletcher32: HDF5 checks every chunk on read, so damaged bytes fail instead of loading
                f.create_dataset(key, data=value, compression=compression, fletcher32=value.size > 0)
            if metadata is not None:
                f.attrs[METADATA_ATTR] = json.dumps(dict(metadata))
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
