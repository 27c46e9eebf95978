"""Small DSRL-layout datasets built by hand for the data-layer tests."""

from __future__ import annotations

import numpy as np


def make_arrays(
    lengths=(3, 2, 4),
    ends=("timeout", "terminal", "timeout"),
    obs_dim: int = 4,
    act_dim: int = 2,
    flag_dtype=np.float32,
    float_dtype=np.float32,
    rewards=None,
    costs=None,
):
    """Episodes back to back; episode i has ``lengths[i]`` steps and ends with ``ends[i]``
    (``"timeout"``, ``"terminal"`` or ``None`` for no flag). Observation k is the row index k, so next
    observations can be checked: next_observations[k] = k + 1 within an episode."""
    n = sum(lengths)
    obs = np.repeat(np.arange(n, dtype=float_dtype)[:, None], obs_dim, axis=1)
    terminals = np.zeros(n, dtype=flag_dtype)
    timeouts = np.zeros(n, dtype=flag_dtype)
    stop = 0
    for length, end in zip(lengths, ends, strict=True):
        stop += length
        if end == "terminal":
            terminals[stop - 1] = 1
        elif end == "timeout":
            timeouts[stop - 1] = 1
    return {
        "observations": obs,
        "next_observations": obs + 1,
        "actions": np.full((n, act_dim), 0.5, dtype=float_dtype),
        "rewards": np.ones(n, dtype=float_dtype) if rewards is None else np.asarray(rewards, float_dtype),
        "costs": np.zeros(n, dtype=float_dtype) if costs is None else np.asarray(costs, float_dtype),
        "terminals": terminals,
        "timeouts": timeouts,
    }
