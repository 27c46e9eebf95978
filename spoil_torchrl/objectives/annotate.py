"""Write the outputs of a frozen module into stored data once, in chunks (e.g. log-ratios, support flags)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import ReplayBuffer
from torchrl.data.replay_buffers.storages import TensorStorage
from tqdm.auto import tqdm


def stored_tensordict(data: TensorDictBase | TensorStorage | ReplayBuffer) -> tuple[TensorDictBase, int]:
    """The tensordict that holds the rows of ``data`` and how many rows are filled."""
    if isinstance(data, ReplayBuffer):
        data = data.storage
    if isinstance(data, TensorStorage):
        if not data.initialized:
            raise ValueError("cannot annotate an empty storage: extend the buffer first")
        # TensorStorage keeps its (capacity-sized) content in ``_storage``; rows past len() are unused.
        return data._storage, len(data)
    if isinstance(data, TensorDictBase):
        if data.batch_dims != 1:
            raise ValueError(
                f"annotate expects a flat batch of transitions, got batch_size {tuple(data.shape)}"
            )
        return data, data.shape[0]
    raise TypeError(
        f"annotate expects a TensorDict, a TensorStorage or a ReplayBuffer, got {type(data).__name__}"
    )


def _module_device(module: torch.nn.Module) -> torch.device | None:
    """Where the module's parameters (or buffers) live; the data are moved there chunk by chunk."""
    for tensor in (*module.parameters(), *module.buffers()):
        return tensor.device
    return None


@torch.no_grad()
def annotate(
    data: TensorDictBase | TensorStorage | ReplayBuffer,
    module: TensorDictModuleBase,
    *,
    chunk_size: int = 65536,
    progress: bool = False,
) -> TensorDictBase:
    """Run ``module`` over every stored row and write its ``out_keys`` into the storage in place.

    Rows are processed ``chunk_size`` at a time, so memory stays bounded for a multi-million-transition
    dataset; each chunk is moved to the module's device (a GPU discriminator annotating a CPU or memory-mapped
    storage) and its outputs back to the storage's. An output key that already exists is overwritten. Works on
    a flat TensorDict, on a TorchRL :class:`~torchrl.data.replay_buffers.TensorStorage` (in-memory or
    memory-mapped), and on a replay buffer that uses one.

    Returns:
        the tensordict that was annotated.

    Examples:
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> data = TensorDict({"observation": torch.arange(5.0).unsqueeze(-1)}, [5])
        >>> double = TensorDictModule(lambda x: 2 * x, in_keys=["observation"], out_keys=["twice"])
        >>> annotate(data, double, chunk_size=2)["twice"].squeeze(-1).tolist()
        [0.0, 2.0, 4.0, 6.0, 8.0]
    """
    if chunk_size <= 0:
        raise ValueError(f"chunk_size must be positive, got {chunk_size}")
    td, n = stored_tensordict(data)
    missing = [k for k in module.in_keys if k not in td.keys(include_nested=True)]
    if missing:
        raise KeyError(f"the stored data has no {missing}; it has {sorted(map(str, td.keys(True, True)))}")
    device = _module_device(module)
    starts = range(0, n, chunk_size)
    for start in tqdm(starts, desc="annotate", disable=not progress, leave=False):
        stop = min(start + chunk_size, n)
        chunk = td[start:stop].select(*module.in_keys)
        chunk = chunk.to(device) if device is not None else chunk.clone()
        out = module(chunk)
        for key in module.out_keys:
            write_rows(td, key, start, out.get(key))
    return td


def write_rows(td: TensorDictBase, key, start: int, value: torch.Tensor) -> None:
    """Write ``value`` into rows ``start:start + len(value)`` of ``td[key]`` in place, creating the key (zeros
    elsewhere) if ``td`` has none; ``td`` may be locked or memory-mapped."""
    value = value.to(td.device) if td.device is not None else value.cpu()
    if key not in td.keys(include_nested=True):
        full = torch.zeros((td.shape[0], *value.shape[1:]), dtype=value.dtype, device=value.device)
        if td.is_locked:
            td.unlock_()
            td.set(key, full)
            td.lock_()
        else:
            td.set(key, full)
        if td.is_memmap():
            td.get(key).copy_(full)
    td.get(key)[start : start + value.shape[0]] = value
