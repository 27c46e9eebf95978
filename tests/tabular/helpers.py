"""Small CMDPs solved by hand, shared by the tabular tests."""

from __future__ import annotations

import numpy as np

from spoil_torchrl.tabular import TabularCMDP


def two_state_cmdp(gamma: float = 0.8) -> TabularCMDP:
    """s0 (start): a0 stays, a1 moves to the absorbing s1 (both of s1's actions stay); reward 1 in s1, cost 1
    on (s0, a1)."""
    transition = np.zeros((2, 2, 2))
    transition[0, 0, 0] = transition[0, 1, 1] = 1.0
    transition[1, :, 1] = 1.0
    reward = np.array([[0.0, 0.0], [1.0, 1.0]])
    cost = np.array([[0.0, 1.0], [0.0, 0.0]])
    return TabularCMDP(transition, reward, cost, [1.0, 0.0], gamma)
