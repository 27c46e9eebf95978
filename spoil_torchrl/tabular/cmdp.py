"""Finite constrained MDPs and their occupancy measures (paper section 3.1).

Occupancies are normalised: :math:`d_\\pi(s,a) = (1-\\gamma)\\sum_t \\gamma^t P(s_t=s, a_t=a)`, so they sum to 1
and :math:`J(\\pi; f) = E_{d_\\pi}[f]` is the paper's normalised return (``f = r``) or cost (``f = c``).
All arrays are float64 NumPy arrays; anything array-like (lists, torch tensors) is accepted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Tolerance for "sums to one" checks of user input.
INPUT_TOL = 1e-6


class InfeasibleProblemError(ValueError):
    """No occupancy measure satisfies the constraints (e.g. the support violates Eq. 14's feasibility)."""


def _as_array(x, name: str, ndim: int) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    return arr


@dataclass(frozen=True)
class TabularCMDP:
    """A finite CMDP :math:`\\langle S, A, T, \\rho_0, r, c, \\gamma \\rangle`.

    Args:
        transition: ``[S, A, S]`` array, ``transition[s, a, s']`` = :math:`T(s'|s,a)`; rows sum to 1.
        reward: ``[S, A]`` reward :math:`r(s,a)`.
        cost: ``[S, A]`` non-negative cost :math:`c(s,a)`.
        init: ``[S]`` initial distribution :math:`\\rho_0`.
        gamma: discount in (0, 1).

    Examples:
        >>> mdp = TabularCMDP(
        ...     transition=[[[1.0, 0.0], [0.0, 1.0]], [[0.0, 1.0], [0.0, 1.0]]],
        ...     reward=[[0.0, 1.0], [0.0, 0.0]], cost=[[0.0, 0.0], [0.0, 0.0]], init=[1.0, 0.0], gamma=0.5)
        >>> mdp.n_states, mdp.n_actions
        (2, 2)
    """

    transition: np.ndarray
    reward: np.ndarray
    cost: np.ndarray
    init: np.ndarray
    gamma: float

    def __post_init__(self) -> None:
        transition = _as_array(self.transition, "transition", 3)
        n_states, n_actions, n_next = transition.shape
        if n_states != n_next or n_states == 0 or n_actions == 0:
            raise ValueError(f"transition must have shape [S, A, S] with S, A > 0, got {transition.shape}")
        if (transition < 0).any() or not np.allclose(transition.sum(-1), 1.0, atol=INPUT_TOL):
            raise ValueError(
                "every transition[s, a, :] must be a probability distribution (non-negative, sum 1)"
            )
        reward = _as_array(self.reward, "reward", 2)
        cost = _as_array(self.cost, "cost", 2)
        for name, arr in (("reward", reward), ("cost", cost)):
            if arr.shape != (n_states, n_actions):
                raise ValueError(f"{name} must have shape {(n_states, n_actions)}, got {arr.shape}")
        if (cost < 0).any():
            raise ValueError("cost must be non-negative (the paper's CMDP has c >= 0)")
        init = _as_array(self.init, "init", 1)
        if init.shape != (n_states,) or (init < 0).any() or abs(init.sum() - 1.0) > INPUT_TOL:
            raise ValueError(f"init must be a probability vector of length {n_states}")
        if not 0.0 < float(self.gamma) < 1.0:
            raise ValueError(f"gamma must lie in (0, 1), got {self.gamma}")
        object.__setattr__(self, "transition", transition)
        object.__setattr__(self, "reward", reward)
        object.__setattr__(self, "cost", cost)
        object.__setattr__(self, "init", init)
        object.__setattr__(self, "gamma", float(self.gamma))

    @property
    def n_states(self) -> int:
        return self.transition.shape[0]

    @property
    def n_actions(self) -> int:
        return self.transition.shape[1]


def check_distribution(mdp: TabularCMDP, d, name: str = "d") -> np.ndarray:
    """Validate a state-action distribution ``[S, A]`` (non-negative, sums to 1) and return it as float64.

    Examples:
        >>> mdp = TabularCMDP([[[1.0]]], [[0.0]], [[0.0]], [1.0], 0.9)
        >>> check_distribution(mdp, [[1.0]]).tolist()
        [[1.0]]
    """
    arr = _as_array(d, name, 2)
    if arr.shape != (mdp.n_states, mdp.n_actions):
        raise ValueError(f"{name} must have shape {(mdp.n_states, mdp.n_actions)}, got {arr.shape}")
    if (arr < 0).any() or abs(arr.sum() - 1.0) > INPUT_TOL:
        raise ValueError(f"{name} must be a distribution over state-action pairs (non-negative, sum 1)")
    return arr


def occupancy(mdp: TabularCMDP, policy) -> np.ndarray:
    """The normalised occupancy :math:`d_\\pi(s,a)` of a stationary policy ``[S, A]`` (rows sum to 1).

    Solves :math:`(I - \\gamma P_\\pi^\\top) d(s) = (1-\\gamma)\\rho_0` with :math:`P_\\pi(s, s') =
    \\sum_a \\pi(a|s) T(s'|s,a)`, then :math:`d(s,a) = d(s)\\pi(a|s)`.

    Examples:
        >>> mdp = TabularCMDP([[[0.0, 1.0]], [[0.0, 1.0]]], [[0.0], [1.0]], [[0.0], [0.0]], [1.0, 0.0], 0.5)
        >>> occupancy(mdp, [[1.0], [1.0]]).ravel().tolist()  # half the mass at t=0 in s0, then s1 forever
        [0.5, 0.5]
    """
    pi = _as_array(policy, "policy", 2)
    if pi.shape != (mdp.n_states, mdp.n_actions):
        raise ValueError(f"policy must have shape {(mdp.n_states, mdp.n_actions)}, got {pi.shape}")
    if (pi < 0).any() or not np.allclose(pi.sum(-1), 1.0, atol=INPUT_TOL):
        raise ValueError("every policy[s, :] must be a probability distribution")
    p_pi = np.einsum("sa,sat->st", pi, mdp.transition)
    lhs = np.eye(mdp.n_states) - mdp.gamma * p_pi.T
    d_state = np.linalg.solve(lhs, (1.0 - mdp.gamma) * mdp.init)
    return np.clip(d_state, 0.0, None)[:, None] * pi


def flow_residual(mdp: TabularCMDP, d) -> np.ndarray:
    """Per-state violation of the Bellman flow constraint (section 3.1) by ``d``:

    :math:`\\sum_a d(s,a) - (1-\\gamma)\\rho_0(s) - \\gamma \\sum_{\\bar s,\\bar a} T(s|\\bar s,\\bar a) d(\\bar s,\\bar a)`.

    Examples:
        >>> mdp = TabularCMDP([[[0.0, 1.0]], [[0.0, 1.0]]], [[0.0], [1.0]], [[0.0], [0.0]], [1.0, 0.0], 0.5)
        >>> float(np.abs(flow_residual(mdp, occupancy(mdp, [[1.0], [1.0]]))).max()) < 1e-12
        True
    """
    d = _as_array(d, "d", 2)
    inflow = np.einsum("sat,sa->t", mdp.transition, d)
    return d.sum(-1) - (1.0 - mdp.gamma) * mdp.init - mdp.gamma * inflow


def policy_from_occupancy(d, *, min_mass: float = 0.0) -> np.ndarray:
    """:math:`\\pi(a|s) = d(s,a) / \\sum_{\\bar a} d(s,\\bar a)`; uniform where a state has no mass (or ``<= min_mass``).

    Examples:
        >>> policy_from_occupancy([[0.125, 0.375], [0.0, 0.0]]).tolist()
        [[0.25, 0.75], [0.5, 0.5]]
    """
    d = np.clip(_as_array(d, "d", 2), 0.0, None)
    mass = d.sum(-1, keepdims=True)
    uniform = np.full_like(d, 1.0 / d.shape[1])
    with np.errstate(invalid="ignore", divide="ignore"):
        pi = np.where(mass > min_mass, d / np.where(mass > 0, mass, 1.0), uniform)
    return pi


def evaluate(mdp: TabularCMDP, d) -> tuple[float, float]:
    """``(J(pi; r), J(pi; c))`` of the policy extracted from ``d`` (appendix E.2), in normalised-occupancy units.

    The policy is evaluated exactly, so ``d`` need not itself be a valid occupancy (filtered BC's is not).

    Examples:
        >>> mdp = TabularCMDP([[[0.0, 1.0]], [[0.0, 1.0]]], [[0.0], [1.0]], [[0.0], [2.0]], [1.0, 0.0], 0.5)
        >>> evaluate(mdp, [[0.5], [0.5]])
        (0.5, 1.0)
    """
    d_pi = occupancy(mdp, policy_from_occupancy(d))
    return float((d_pi * mdp.reward).sum()), float((d_pi * mdp.cost).sum())


def total_variation(d1, d2) -> float:
    """Total-variation distance :math:`\\frac12 \\sum |d_1 - d_2|` between two state-action distributions.

    Examples:
        >>> total_variation([[0.5, 0.5]], [[1.0, 0.0]])
        0.5
    """
    return 0.5 * float(np.abs(_as_array(d1, "d1", 2) - _as_array(d2, "d2", 2)).sum())
