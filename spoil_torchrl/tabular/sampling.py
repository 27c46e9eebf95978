"""Draw transitions from tabular occupancies as TorchRL TED-layout tensordicts with one-hot features."""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict

from spoil_torchrl.tabular.cmdp import TabularCMDP, check_distribution


def one_hot(index: np.ndarray | torch.Tensor, n: int) -> torch.Tensor:
    """Float32 one-hot rows for integer ``index``.

    Examples:
        >>> one_hot(np.array([1, 0]), 3).tolist()
        [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]
    """
    return torch.nn.functional.one_hot(torch.as_tensor(index, dtype=torch.long), n).to(torch.float32)


def sample_transitions(mdp: TabularCMDP, d, n: int, rng: np.random.Generator) -> TensorDict:
    """``n`` i.i.d. transitions :math:`(s, a) \\sim d`, :math:`s' \\sim T(\\cdot|s,a)` in the TED layout.

    Keys: ``observation`` / ``action`` / ``("next", "observation")`` (one-hot), ``("next", "reward")``,
    ``("next", "cost")`` (float32, trailing dim 1), ``("next", "terminated" | "truncated" | "done")`` (all
    False: the tabular CMDPs are infinite-horizon), and the integer ``state``, ``action_index`` and
    ``("next", "state")``.

    Examples:
        >>> from spoil_torchrl.tabular.problems import random_dual_demo_problem
        >>> problem = random_dual_demo_problem(seed=0)
        >>> td = sample_transitions(problem.mdp, problem.d_U, 5, np.random.default_rng(0))
        >>> td["observation"].shape, td["next", "reward"].shape
        (torch.Size([5, 6]), torch.Size([5, 1]))
    """
    d = check_distribution(mdp, d)
    if n <= 0:
        raise ValueError(f"n must be positive, got {n}")
    n_s, n_a = mdp.n_states, mdp.n_actions
    pair = rng.choice(n_s * n_a, size=n, p=d.ravel() / d.sum())
    s, a = np.divmod(pair, n_a)
    cdf = np.cumsum(mdp.transition[s, a], axis=1)
    s_next = np.minimum((rng.uniform(size=(n, 1)) > cdf).sum(axis=1), n_s - 1)
    flags = torch.zeros(n, 1, dtype=torch.bool)
    return TensorDict(
        {
            "observation": one_hot(s, n_s),
            "action": one_hot(a, n_a),
            "state": torch.as_tensor(s),
            "action_index": torch.as_tensor(a),
            "next": {
                "observation": one_hot(s_next, n_s),
                "state": torch.as_tensor(s_next),
                "reward": torch.as_tensor(mdp.reward[s, a], dtype=torch.float32).unsqueeze(-1),
                "cost": torch.as_tensor(mdp.cost[s, a], dtype=torch.float32).unsqueeze(-1),
                "terminated": flags,
                "truncated": flags.clone(),
                "done": flags.clone(),
            },
        },
        batch_size=[n],
    )


def sample_initial_states(mdp: TabularCMDP, n: int, rng: np.random.Generator) -> TensorDict:
    """``n`` initial states :math:`s_0 \\sim \\rho_0` as one-hot ``observation`` rows (plus integer ``state``).

    Examples:
        >>> from spoil_torchrl.tabular.problems import random_cmdp
        >>> sample_initial_states(random_cmdp(3, 2, seed=0), 4, np.random.default_rng(0))["state"].tolist()
        [0, 0, 0, 0]
    """
    s = rng.choice(mdp.n_states, size=n, p=mdp.init)
    return TensorDict({"observation": one_hot(s, mdp.n_states), "state": torch.as_tensor(s)}, batch_size=[n])
