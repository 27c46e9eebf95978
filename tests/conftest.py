"""Shared fixtures: small role-structured batches in the TED layout."""

from __future__ import annotations

import os

import pytest
import torch
from filelock import FileLock
from tensordict import TensorDict

OBS_DIM, ACT_DIM = 5, 2


def transitions(n: int, obs_dim: int = OBS_DIM, act_dim: int = ACT_DIM) -> TensorDict:
    """``n`` random transitions with every key the losses read."""
    return TensorDict(
        {
            "observation": torch.randn(n, obs_dim),
            "action": torch.rand(n, act_dim) * 2 - 1,
            "next": {
                "observation": torch.randn(n, obs_dim),
                "reward": torch.randn(n, 1),
                "cost": torch.rand(n, 1),
                "terminated": torch.zeros(n, 1, dtype=torch.bool),
                "truncated": torch.zeros(n, 1, dtype=torch.bool),
                "done": torch.zeros(n, 1, dtype=torch.bool),
            },
            "log_ratio_performant": torch.randn(n, 1),
            "safe_support": torch.randint(0, 2, (n, 1)).float(),
        },
        batch_size=[n],
    )


def dual_batch(n_safe: int = 16, n_perf: int = 12, n_unl: int = 32, n_init: int = 8) -> TensorDict:
    """A batch with the four roles of a dual-demonstration sample."""
    return TensorDict(
        {
            "safe": transitions(n_safe),
            "performant": transitions(n_perf),
            "unlabeled": transitions(n_unl),
            "init": TensorDict({"observation": torch.randn(n_init, OBS_DIM)}, [n_init]),
        },
        batch_size=[],
    )


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


@pytest.fixture(autouse=True, scope="session")
def _one_thread():
    # Small networks gain nothing from intra-op threads, and spinning threads slow everything down badly when
    # another process shares the 2 cores.
    torch.set_num_threads(1)


@pytest.fixture
def batch() -> TensorDict:
    return dual_batch()


def grads_of(module_params) -> list[torch.Tensor | None]:
    return [p.grad for p in module_params]


@pytest.fixture(scope="session")
def tiny_pc1_dataset(tmp_path_factory):
    """A small collected PointCircle1 file (3 episodes of each policy type) with the collector's metadata."""
    import importlib.util

    if importlib.util.find_spec("safety_gymnasium") is None:
        pytest.skip("safety-gymnasium not installed")
    from spoil_torchrl.data import POOLS, Segment, collect

    segments = [Segment(pool, f"zoo:{pool}", 3) for pool in POOLS]
    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        path = tmp_path_factory.mktemp("data") / "tiny-pc1.hdf5"
    else:  # under pytest -n, one file for all the workers: the first one to get here makes it
        path = tmp_path_factory.getbasetemp().parent / "tiny-pc1.hdf5"
    with FileLock(f"{path}.lock"):
        if path.is_file():
            return path
        return collect(
            "SafetyPointCircle1-v0", segments, path, seed=0, num_envs=3, reference_episodes=2, progress=False
        )


#: Modules whose doctests need an optional extra: (module file, the import that decides, the extra).
OPTIONAL_DOCTESTS = (("spoil_torchrl/eval/aggregate.py", "rliable", "report"),)


def pytest_collection_modifyitems(config, items):
    """Skip the doctests of a module whose optional extra is not installed (``make EXTRAS=dev``)."""
    import importlib.util

    for path, module, extra in OPTIONAL_DOCTESTS:
        if importlib.util.find_spec(module) is not None:
            continue
        marker = pytest.mark.skip(reason=f"needs the {extra!r} extra ({module} is not installed)")
        for item in items:
            if str(item.path).endswith(path):
                item.add_marker(marker)
