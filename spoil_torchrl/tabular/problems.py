"""Random finite CMDPs with safe / performant / unlabeled demonstration distributions, for exact checks."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spoil_torchrl.tabular.cmdp import TabularCMDP, occupancy


@dataclass(frozen=True)
class DualDemoProblem:
    """A CMDP with the three demonstration distributions of IL-SP (section 4.1) and the policies behind them.

    ``d_P`` comes from a reward-seeking policy that also takes costly actions, ``d_S`` from a policy that never
    takes a costly action (so ``supp(d_S)`` excludes every costly pair), and ``d_U`` is an equal mixture of the
    performant, the safe and the uniform policy's occupancies (full support, so every ratio ``d/d_U`` is
    finite). With several constraints (``random_dual_demo_problem(constraints=K)``) ``d_S`` and ``pi_S`` hold one safe
    distribution and policy per constraint (``[K, S, A]``) and the CMDP's cost is 1 where any constraint's is.
    """

    mdp: TabularCMDP
    d_P: np.ndarray
    d_S: np.ndarray
    d_U: np.ndarray
    pi_P: np.ndarray
    pi_S: np.ndarray
    costs: np.ndarray | None = None  # [K, S, A]: each constraint's cost, with several constraints


def random_cmdp(
    n_states: int,
    n_actions: int,
    *,
    seed: int,
    gamma: float = 0.9,
    cost_fraction: float = 0.3,
    slip: float = 1.0,
) -> TabularCMDP:
    """A random CMDP: uniform rewards in [0, 1], cost 1 on a random ``cost_fraction`` of the pairs (never on
    every action of a state), one initial state. Each action leads to a random "intended" next state with
    probability ``1 - slip`` and to a Dirichlet(1)-random next state otherwise (``slip=1``: dense random
    transitions; the paper's gridworld has ``slip=0.01``).

    Examples:
        >>> mdp = random_cmdp(4, 3, seed=0)
        >>> mdp.transition.shape, bool((mdp.cost.min(axis=1) == 0).all())
        ((4, 3, 4), True)
    """
    if n_states < 1 or n_actions < 2:
        raise ValueError("a random CMDP needs at least one state and two actions")
    rng = np.random.default_rng(seed)
    if not 0.0 <= slip <= 1.0:
        raise ValueError(f"slip must lie in [0, 1], got {slip}")
    intended = np.eye(n_states)[rng.integers(n_states, size=(n_states, n_actions))]
    transition = (1.0 - slip) * intended + slip * rng.dirichlet(np.ones(n_states), size=(n_states, n_actions))
    reward = rng.uniform(size=(n_states, n_actions))
    cost = (rng.uniform(size=(n_states, n_actions)) < cost_fraction).astype(np.float64)
    for s in range(n_states):  # keep at least one cost-free action per state
        if cost[s].all():
            cost[s, rng.integers(n_actions)] = 0.0
    init = np.zeros(n_states)
    init[0] = 1.0
    return TabularCMDP(transition, reward, cost, init, gamma)


def softmax_policy(logits: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Row-wise softmax of ``logits`` ``[S, A]``, with probability 0 where ``mask`` is False.

    Examples:
        >>> softmax_policy(np.zeros((1, 2)), mask=np.array([[True, False]])).tolist()
        [[1.0, 0.0]]
    """
    z = np.where(mask, logits, -np.inf) if mask is not None else logits
    z = z - z.max(axis=1, keepdims=True)
    p = np.exp(z)
    return p / p.sum(axis=1, keepdims=True)


def random_dual_demo_problem(
    n_states: int = 6,
    n_actions: int = 3,
    *,
    seed: int,
    gamma: float = 0.9,
    temperature: float = 0.3,
    slip: float = 1.0,
    constraints: int = 1,
) -> DualDemoProblem:
    """A :func:`random_cmdp` with IL-SP demonstration distributions (see :class:`DualDemoProblem`).

    The performant policy is a softmax of the immediate reward with ``temperature``; the safe policy is a
    random softmax restricted to cost-free actions. With ``constraints`` K > 1 (``docs/several_constraints.md``)
    there are K costs and K safe demonstrators (:func:`_several_constraints`).

    Examples:
        >>> problem = random_dual_demo_problem(seed=0)
        >>> float((problem.d_S * problem.mdp.cost).sum()), bool((problem.d_U > 0).all())
        (0.0, True)
        >>> problem = random_dual_demo_problem(seed=0, constraints=2)
        >>> problem.d_S.shape, [float((d * c).sum()) for d, c in zip(problem.d_S, problem.costs)]
        ((2, 6, 3), [0.0, 0.0])
    """
    if isinstance(constraints, bool) or not isinstance(constraints, int) or constraints < 1:
        raise ValueError(f"constraints must be an integer >= 1, got {constraints!r}")
    mdp = random_cmdp(n_states, n_actions, seed=seed, gamma=gamma, slip=slip)
    rng = np.random.default_rng(seed + 1)
    if constraints > 1:
        return _several_constraints(mdp, rng, constraints, temperature)
    pi_P = softmax_policy(mdp.reward / temperature)
    pi_S = softmax_policy(rng.normal(size=(n_states, n_actions)), mask=mdp.cost == 0)
    pi_uniform = np.full((n_states, n_actions), 1.0 / n_actions)
    d_P, d_S = occupancy(mdp, pi_P), occupancy(mdp, pi_S)
    d_U = (d_P + d_S + occupancy(mdp, pi_uniform)) / 3.0
    return DualDemoProblem(mdp, d_P, d_S, d_U, pi_P, pi_S)


def _several_constraints(
    mdp: TabularCMDP,
    rng: np.random.Generator,
    constraints: int,
    temperature: float,
    cost_fraction: float = 0.3,
) -> DualDemoProblem:
    """The problem of :func:`random_dual_demo_problem` with ``constraints`` costs and one safe demonstrator per
    constraint. Constraint 0's cost is ``mdp``'s; each further constraint costs 1 on its own random
    ``cost_fraction`` of the pairs. One action per state is free of every cost, so a policy can respect all of
    them. Safe demonstrator ``k`` is a random softmax over the actions free of cost ``k`` only: it respects its
    constraint and may break the others. ``d_U`` mixes the performant, every safe and the uniform occupancy, and
    the returned CMDP's cost is 1 where any constraint's is."""
    costs = [mdp.cost] + [
        (rng.uniform(size=mdp.cost.shape) < cost_fraction).astype(np.float64) for _ in range(constraints - 1)
    ]
    for s in range(mdp.n_states):  # one action per state free of every cost: constraint 0's first free action
        free = int(np.flatnonzero(mdp.cost[s] == 0)[0])
        for cost in costs[1:]:
            cost[s, free] = 0.0
    mdp = TabularCMDP(mdp.transition, mdp.reward, np.max(costs, axis=0), mdp.init, mdp.gamma)
    n_states, n_actions = mdp.n_states, mdp.n_actions
    pi_P = softmax_policy(mdp.reward / temperature)
    pi_S = np.stack([softmax_policy(rng.normal(size=(n_states, n_actions)), mask=c == 0) for c in costs])
    d_S = np.stack([occupancy(mdp, pi) for pi in pi_S])
    pi_uniform = np.full((n_states, n_actions), 1.0 / n_actions)
    d_P = occupancy(mdp, pi_P)
    d_U = (d_P + d_S.sum(axis=0) + occupancy(mdp, pi_uniform)) / (constraints + 2.0)
    return DualDemoProblem(mdp, d_P, d_S, d_U, pi_P, pi_S, costs=np.stack(costs))
