"""``DualDemoBuffers``: one TorchRL replay buffer per IL-SP role plus one of initial states."""

from __future__ import annotations

import numbers
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.data import TensorDictReplayBuffer
from torchrl.data.replay_buffers import RandomSampler
from torchrl.data.replay_buffers.storages import TensorStorage

from spoil_torchrl.data.episodes import select_episodes
from spoil_torchrl.objectives.annotate import annotate, stored_tensordict, write_rows


def _episode_ids(role: str, ids) -> torch.Tensor:
    """``ids`` as int64 episode indices, refused when they are not whole numbers (a float id would be truncated
    to another episode) or are a boolean mask."""
    values = ids if isinstance(ids, torch.Tensor) else torch.as_tensor(np.asarray(ids))  # float64, as given
    if values.dtype == torch.bool:
        raise ValueError(f"role {role!r}: episode ids expected, got a boolean mask (use mask.nonzero())")
    if values.is_floating_point() and not bool((values.isfinite() & (values == values.round())).all()):
        raise ValueError(f"role {role!r}: episode ids must be whole numbers, got {values.tolist()[:10]}")
    return values.to(torch.int64)


def _role_data(episodes: TensorDict, ids: torch.Tensor) -> TensorDict:
    """The role's transitions; all episodes -> the dataset itself (no copy)."""
    n_episodes = int(episodes["episode"].max()) + 1
    if ids.numel() == n_episodes and bool((torch.sort(ids).values == torch.arange(n_episodes)).all()):
        return episodes
    return select_episodes(episodes, ids)


class DualDemoBuffers:
    """Replay buffers for dual-demonstration training: ``sample()`` returns one TensorDict with a batch per role.

    Each role's transitions (selected from ``episodes`` by episode ids) live in a TorchRL
    :class:`~torchrl.data.TensorDictReplayBuffer` whose storage wraps them without a further copy (a role that
    holds every episode shares the dataset's own memory, memory-mapped or not). The ``"init"`` buffer holds the
    first observation of each episode of ``init_role`` (:math:`\\rho_0`, the initial-state term of the DICE
    duals). Sampling is uniform with replacement and reproducible: buffer ``i`` draws from
    ``torch.Generator(device).manual_seed(seed + i)``.

    Args:
        episodes: TED-layout transitions with ``episode`` and ``is_init`` (from
            :func:`~spoil_torchrl.data.load_episodes`).
        roles: role name -> episode ids (e.g. from :func:`~spoil_torchrl.data.label_ilsp` / ``draw``).

    Keyword Args:
        batch_size: per-role batch size, an int for all roles or a mapping (missing roles get 512).
        init_role: role whose episodes give the initial states. Default ``"unlabeled"``.
        memmap_dir: memory-map the copied role subsets into this folder (the all-episodes role stays as loaded).
        seed: base seed of the buffers' generators.
        device: where the roles' transitions live and their indices are drawn (``None`` or a CPU: where
            ``episodes`` are, without a copy). On a GPU each role is copied there once, and a batch is drawn and
            gathered there, with no transfer per sample.

    Examples:
        >>> import numpy as np
        >>> from spoil_torchrl.data.episodes import episodes_from_arrays
        >>> n = 6
        >>> episodes = episodes_from_arrays({
        ...     "observations": np.random.randn(n, 3).astype(np.float32),
        ...     "next_observations": np.random.randn(n, 3).astype(np.float32),
        ...     "actions": np.zeros((n, 2), np.float32), "rewards": np.ones(n, np.float32),
        ...     "costs": np.zeros(n, np.float32), "terminals": np.zeros(n, np.float32),
        ...     "timeouts": np.array([0, 1, 0, 1, 0, 1], np.float32)})
        >>> buffers = DualDemoBuffers(episodes, {"safe": [0], "performant": [1], "unlabeled": [0, 1, 2]},
        ...                           batch_size={"safe": 4, "performant": 4, "unlabeled": 8, "init": 2})
        >>> batch = buffers.sample()
        >>> batch["unlabeled"].shape, batch["init"].shape, len(buffers["init"])
        (torch.Size([8]), torch.Size([2]), 3)
    """

    def __init__(
        self,
        episodes: TensorDict,
        roles: Mapping[str, object],
        *,
        batch_size: int | Mapping[str, int] = 512,
        init_role: str = "unlabeled",
        memmap_dir: str | os.PathLike | None = None,
        seed: int = 0,
        device: torch.device | str | None = None,
    ) -> None:
        if "init" in roles:
            raise ValueError("'init' is reserved for the initial-state buffer")
        if init_role not in roles:
            raise ValueError(f"init_role {init_role!r} is not one of the roles {list(roles)}")
        sizes = (
            {r: batch_size for r in [*roles, "init"]}
            if isinstance(batch_size, numbers.Integral)
            else dict(batch_size)
        )
        for role, size in sizes.items():
            if isinstance(size, bool) or not isinstance(size, numbers.Integral) or size < 1:
                raise ValueError(f"batch_size of role {role!r} = {size!r}: expected an integer >= 1")
            sizes[role] = int(size)
        self.buffers: dict[str, TensorDictReplayBuffer] = {}
        self._generators: dict[str, torch.Generator] = {}
        for i, (role, ids) in enumerate([*roles.items(), ("init", None)]):
            if role == "init":
                data = _role_data(episodes, _episode_ids(init_role, roles[init_role]))
                data = data[data["is_init"].squeeze(-1)].select("observation", "episode")
            else:
                data = _role_data(episodes, _episode_ids(role, ids))
                if data is not episodes and memmap_dir is not None:
                    data = data.memmap_(Path(memmap_dir) / role)
            if data.shape[0] == 0:
                raise ValueError(f"role {role!r} has no transitions")
            if device is not None and torch.device(device).type != "cpu":
                data = data.to(device)  # once; a batch is then drawn and gathered on the device
            self._generators[role] = torch.Generator(device or "cpu").manual_seed(seed + i)
            self.buffers[role] = TensorDictReplayBuffer(
                storage=TensorStorage(data),
                sampler=RandomSampler(),
                batch_size=sizes.get(role, 512),
                generator=self._generators[role],
            )

    @property
    def roles(self) -> list[str]:
        return list(self.buffers)

    @property
    def device(self) -> torch.device:
        """Where the transitions live and the batches are drawn."""
        return next(iter(self._generators.values())).device

    def __getitem__(self, role: str) -> TensorDictReplayBuffer:
        return self.buffers[role]

    def sample(self, roles: Sequence[str] | None = None) -> TensorDict:
        """One batch per role, ``TensorDict({role: batch, ..., "init": batch}, batch_size=[])``; with ``roles``,
        of those roles only (what a stage's losses read: :func:`~spoil_torchrl.objectives.keys.roles_read`).
        Each role draws from its own generator, so leaving a role out changes no other role's batches.

        Examples:
            >>> from tensordict import TensorDict
            >>> episodes = TensorDict({"observation": torch.randn(4, 2), "episode": torch.tensor([0, 0, 1, 1]),
            ...                        "is_init": torch.tensor([[True], [False], [True], [False]])}, [4])
            >>> buffers = DualDemoBuffers(episodes, {"safe": [0], "unlabeled": [0, 1]}, batch_size=3)
            >>> sorted(buffers.sample(["unlabeled", "init"]).keys())
            ['init', 'unlabeled']
        """
        if roles is None:
            roles = self.roles
        elif unknown := sorted(set(roles) - set(self.buffers)):
            raise ValueError(f"no buffer for roles {unknown}; the buffers hold {self.roles}")
        wanted = set(roles)
        return TensorDict(
            {role: buffer.sample() for role, buffer in self.buffers.items() if role in wanted}, batch_size=[]
        )

    def rng_state(self) -> dict[str, torch.Tensor]:
        """Every buffer's sampling-generator state (role -> state), for bit-exact resumption.

        Examples:
            >>> from tensordict import TensorDict
            >>> episodes = TensorDict({"observation": torch.randn(4, 2), "episode": torch.tensor([0, 0, 1, 1]),
            ...                        "is_init": torch.tensor([[True], [False], [True], [False]])}, [4])
            >>> buffers = DualDemoBuffers(episodes, {"unlabeled": [0, 1]}, batch_size=3)
            >>> state = buffers.rng_state()
            >>> first = buffers.sample()["unlabeled", "observation"]
            >>> buffers.set_rng_state(state)
            >>> bool((buffers.sample()["unlabeled", "observation"] == first).all())
            True
        """
        return {role: generator.get_state() for role, generator in self._generators.items()}

    def set_rng_state(self, state: Mapping[str, torch.Tensor]) -> None:
        """Restore what :meth:`rng_state` returned (the same roles, in any order)."""
        if set(state) != set(self._generators):
            raise ValueError(
                f"rng state for roles {sorted(state)}, but the buffers hold {sorted(self._generators)}"
            )
        for role, generator in self._generators.items():
            generator.set_state(state[role])

    def annotate(
        self,
        role: str,
        module: TensorDictModuleBase | str,
        fn: Callable[[TensorDict], torch.Tensor] | None = None,
        *,
        chunk_size: int = 65536,
    ) -> None:
        """Write derived keys into ``role``'s storage once, in chunks.

        Either ``annotate(role, module)`` with a module that writes its ``out_keys`` (e.g.
        :class:`~spoil_torchrl.objectives.LogRatio`, :class:`~spoil_torchrl.objectives.SupportEstimator`), or
        ``annotate(role, key, fn)`` with ``fn`` mapping a chunk of stored transitions to the values of ``key``.
        """
        if isinstance(module, str):
            if fn is None:
                raise TypeError("annotate(role, key, fn) needs fn")
            module = _KeyFunction(module, fn, self.buffers[role].storage)
        annotate(self.buffers[role], module, chunk_size=chunk_size)

    def set_annotation(self, role: str, key: str, values: torch.Tensor) -> None:
        """Write ``values`` (one row per stored transition of ``role``, in storage order) as ``key`` of the
        role's storage: what :meth:`annotate` wrote once, stored and written back (a resumed run's stored
        pre-training)."""
        td, n = stored_tensordict(self.buffers[role])
        if values.shape[0] != n:
            raise ValueError(f"{key!r} has {values.shape[0]} rows, but role {role!r} stores {n} transitions")
        write_rows(td, key, 0, values)


class _KeyFunction(TensorDictModuleBase):
    """Adapts ``fn(chunk) -> tensor`` to the module interface :func:`annotate` expects."""

    def __init__(self, key: str, fn: Callable[[TensorDict], torch.Tensor], storage) -> None:
        super().__init__()
        self.fn = fn
        self.in_keys = [k for k in storage._storage.keys(True, True)]
        self.out_keys = [key]

    def forward(self, tensordict: TensorDict) -> TensorDict:
        tensordict.set(self.out_keys[0], self.fn(tensordict))
        return tensordict
