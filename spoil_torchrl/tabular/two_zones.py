"""A gridworld with two kinds of zones, each with its own cost: the K = 2 check of ``docs/several_constraints.md``
on a problem with a return/safety trade-off.

The layout is :mod:`~spoil_torchrl.tabular.gridworld`'s ``"across"`` one (start and goal in the middles of the
left and right edges, 3 x 3 zones centred on the main diagonal, the chosen move w.p. ``1 - slip``), with one zone
of kind A and one of kind B. Their centres are drawn per seed among the :func:`trade_off_layouts`: for each kind,
the shortest route that avoids that kind alone crosses the other kind's zone and is shorter than every route
that avoids both (7 x 7, the default, is the smallest grid that has such a layout). Cost k is
:func:`~spoil_torchrl.tabular.gridworld.zone_cost` of kind k's zone (``"crossing"``: the chosen move into a
kind-k cell from outside it); the CMDP's cost is their maximum. Zones may touch: on the 7 x 7 grid the two
layouts' zones share their corner cell (3, 3), whose entry costs on both kinds.

The demonstrations (:func:`two_zone_problem`) come from four experts, the LP optima of
:mod:`~spoil_torchrl.tabular.optimal` with no cost, cost A only, cost B only and both (cost limit 0, so the
constrained experts never choose a costly action; :func:`expert_policies`):

- d_P: the four experts with action noise (a uniform action w.p. ``noise``), ``(1 - safeness) / 3`` each for the
  first three and ``safeness`` for the last. The single-kind experts put performant mass on the routes that
  respect one kind and cross the other (with the unconstrained and both-kinds experts alone, the total variation
  between the exact solutions with one and two constraints is about half as large). The noise gives every
  state that slips reach an action inside both safe supports; without it a state inside a zone can be left
  with none, and then (slips lead there from every neighbour) no occupancy fits the supports.
- d_S^k: ``performance`` parts experts that respect kind k, the kind-k expert and (share ``shared``) the
  both-kinds expert, whose demonstrations belong to both safe sets; ``1 - performance`` parts the careful random
  policy that avoids kind-k zones only (:func:`~spoil_torchrl.tabular.gridworld.safe_random_policy`). Safe set k
  respects its own kind and crosses the other. Without the shared expert each safe set sees the route that
  avoids both kinds only through its random walker, and the learned kappa-cuts drop pairs on it.
- d_U: the equal mixture of d_P, d_S^A, d_S^B and the uniform policy's occupancy (positive on every pair).

At the goal and in the absorbing state every action is equivalent; every expert takes them uniformly there, so
that the absorbing state's mass (about half) carries no arbitrary LP tie-break.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from spoil_torchrl.tabular.cmdp import TabularCMDP, occupancy, policy_from_occupancy
from spoil_torchrl.tabular.gridworld import (
    LAYOUTS,
    MOVES,
    Gridworld,
    grid_transition,
    route_lengths,
    safe_distribution,
    safe_random_policy,
    uniform_policy,
    zone_candidates,
    zone_cells,
    zone_cost,
)
from spoil_torchrl.tabular.optimal import solve_cmdp_optimum, solve_mdp_optimum
from spoil_torchrl.tabular.problems import DualDemoProblem

#: The names of the two zone kinds, in the order of ``costs``, ``d_S`` and ``zones``.
KINDS = ("A", "B")


@dataclass(frozen=True)
class TwoZoneGridworld:
    """The two-zone gridworld: ``grid`` has the union of the zones and the CMDP with the maximum of the two costs
    (``grid.zone_centers`` is ``(k_A, k_B)``); ``zones`` ``[2, S]`` and ``costs`` ``[2, S, A]`` are per kind."""

    grid: Gridworld
    zones: np.ndarray
    costs: np.ndarray

    @property
    def mdp(self) -> TabularCMDP:
        return self.grid.mdp

    def kind(self, k: int) -> Gridworld:
        """The gridworld of zone kind ``k`` alone: its zone, and the CMDP with cost ``k`` only.

        Examples:
            >>> world = make_two_zone_gridworld(0)
            >>> world.kind(0).zone_centers, bool((world.kind(0).mdp.cost == world.costs[0]).all())
            ((4,), True)
        """
        mdp = dataclasses.replace(self.mdp, cost=self.costs[k])
        center = (self.grid.zone_centers[k],)
        return dataclasses.replace(self.grid, mdp=mdp, zone_centers=center, zone=self.zones[k])


def trade_off_layouts(grid: Gridworld) -> list[tuple[int, int]]:
    """The zone centres ``(k_A, k_B)`` (distinct :func:`~spoil_torchrl.tabular.gridworld.zone_candidates` of
    ``grid``'s size, start and goal; ``grid``'s own zones are ignored) where both zone kinds matter: for each kind,
    the shortest route that never enters that kind's zone is shorter than the shortest route that enters neither
    (:func:`~spoil_torchrl.tabular.gridworld.route_lengths`), so respecting one kind alone means crossing the
    other.

    Examples:
        >>> from spoil_torchrl.tabular.gridworld import make_gridworld
        >>> trade_off_layouts(make_gridworld(0, size=7, n_zones=0))  # (2, 3): avoiding B alone is as long
        [(2, 4), (4, 2)]
    """
    candidates = zone_candidates(grid.size, grid.start, grid.goal)

    def free_route(zone: np.ndarray) -> int | None:
        return route_lengths(dataclasses.replace(grid, zone=zone))[1]

    layouts = []
    for a in candidates:
        for b in candidates:
            if a == b:
                continue
            zone_a, zone_b = zone_cells(grid.size, [a]), zone_cells(grid.size, [b])
            both = free_route(zone_a | zone_b)
            if both is not None and free_route(zone_a) < both and free_route(zone_b) < both:
                layouts.append((a, b))
    return layouts


def make_two_zone_gridworld(
    seed: int,
    *,
    size: int = 7,
    centers: tuple[int, int] | None = None,
    start: tuple[int, int] | None = None,
    goal: tuple[int, int] | None = None,
    slip: float = 0.01,
    gamma: float = 0.95,
) -> TwoZoneGridworld:
    """The two-zone gridworld of one seed (see the module docstring).

    Args:
        seed: draws the diagonal indices ``(k_A, k_B)`` of the two zones' centres uniformly among the
            :func:`trade_off_layouts` (``np.random.default_rng(seed)``) when ``centers`` is ``None``.
        size: cells a side, at least 6 (7 at least for a drawn layout).
        centers: ``(k_A, k_B)`` to place the zones by hand instead (any layout with a cost-free route).
        start, goal: default to the ``"across"`` layout's, ``(size // 2, 0)`` and ``(size // 2, size - 1)``.
        slip, gamma: as :func:`~spoil_torchrl.tabular.gridworld.make_gridworld`.

    Raises:
        ValueError: ``size`` below 6 or without a trade-off layout, start or goal off the grid, equal or inside a
            zone, ``centers`` not two distinct cells of the grid, or zones that leave no cost-free route from start
            to goal.

    Examples:
        >>> world = make_two_zone_gridworld(0)
        >>> world.grid.zone_centers, world.mdp.n_states, world.costs.shape
        ((4, 2), 50, (2, 50, 4))
        >>> bool((world.mdp.cost == world.costs.max(axis=0)).all())
        True
        >>> make_two_zone_gridworld(0, size=6, centers=(1, 4), start=(5, 0), goal=(0, 5))
        Traceback (most recent call last):
        ...
        ValueError: the zones at (1, 1) and (4, 4) leave no cost-free route from (5, 0) to (0, 5)
    """
    if isinstance(size, bool) or not isinstance(size, int) or size < 6:
        raise ValueError(f"size must be an integer >= 6 (room for two zones off the corners), got {size!r}")
    default_start, default_goal, _ = LAYOUTS["across"](size)
    start = default_start if start is None else tuple(start)
    goal = default_goal if goal is None else tuple(goal)
    for name, (r, c) in (("start", start), ("goal", goal)):
        if not (0 <= r < size and 0 <= c < size):
            raise ValueError(f"{name} {(r, c)} lies outside the {size} x {size} grid")
    if start == goal:
        raise ValueError("start and goal must differ")
    transition = grid_transition(size, goal, slip)
    reward = np.zeros((size * size + 1, len(MOVES)))
    reward[goal[0] * size + goal[1]] = 1.0
    init = np.zeros(size * size + 1)
    init[start[0] * size + start[1]] = 1.0
    free = TabularCMDP(transition, reward, np.zeros_like(reward), init, gamma)  # no zone yet
    empty = Gridworld(free, size, start, goal, (), np.zeros(size * size + 1, dtype=bool), 0.0)
    if centers is None:
        layouts = trade_off_layouts(empty)
        if not layouts:
            raise ValueError(
                f"no two zone centres of a {size} x {size} grid with start {start} and goal {goal} make both zone "
                "kinds matter; use a larger grid or give centers"
            )
        centers = layouts[int(np.random.default_rng(seed).integers(len(layouts)))]
    centers = tuple(int(k) for k in centers)
    if len(centers) != 2 or centers[0] == centers[1]:
        raise ValueError(f"centers must be two distinct diagonal indices (k_A, k_B), got {centers}")
    zones = np.stack([zone_cells(size, [k]) for k in centers])
    union = zones.any(axis=0)
    for name, (r, c) in (("start", start), ("goal", goal)):
        if union[r * size + c]:
            raise ValueError(f"the {name} {(r, c)} lies inside a zone")
    costs = np.stack([zone_cost(transition, zone) for zone in zones])
    mdp = dataclasses.replace(free, cost=costs.max(axis=0))
    grid = dataclasses.replace(empty, mdp=mdp, zone_centers=centers, zone=union)
    if route_lengths(grid)[1] is None:  # a route that never enters the union never pays either cost
        where = " and ".join(f"({k}, {k})" for k in centers)
        raise ValueError(f"the zones at {where} leave no cost-free route from {start} to {goal}")
    return TwoZoneGridworld(grid, zones, costs)


def expert_policies(world: TwoZoneGridworld) -> dict[str, np.ndarray]:
    """The optimal policies of the LPs of :mod:`~spoil_torchrl.tabular.optimal`, ``[S, A]`` each: ``"none"``
    (no cost), ``"A"``, ``"B"`` (that kind's cost only) and ``"both"`` (the maximum of the two), with cost limit
    0, so the constrained ones never choose a costly action. Uniform at the goal and the absorbing state, where
    every action is equivalent.

    Examples:
        >>> policies = expert_policies(make_two_zone_gridworld(0))
        >>> sorted(policies), policies["both"].shape
        (['A', 'B', 'both', 'none'], (50, 4))
    """
    mdp = world.mdp
    costs = {"none": np.zeros_like(mdp.cost), **dict(zip(KINDS, world.costs, strict=True)), "both": mdp.cost}
    policies = {}
    for name, cost in costs.items():
        constrained = dataclasses.replace(mdp, cost=cost)
        d = solve_mdp_optimum(mdp) if name == "none" else solve_cmdp_optimum(constrained, 0.0)
        # where the LP leaves a state without mass its policy is uniform; keep it off the costly actions there too
        policy = np.where(cost > 0, 0.0, policy_from_occupancy(d))
        # a state whose LP mass is round-off on costly actions only: its cost-free actions (every state has one)
        stuck = policy.sum(axis=1) == 0
        policy[stuck] = cost[stuck] == 0
        policy[[world.grid.cell(*world.grid.goal), world.grid.absorbing]] = 1.0
        policies[name] = policy / policy.sum(axis=1, keepdims=True)
    return policies


def two_zone_problem(
    world: TwoZoneGridworld,
    *,
    safeness: float = 0.25,
    performance: float = 0.5,
    noise: float = 0.1,
    shared: float = 0.5,
) -> DualDemoProblem:
    """The IL-SP distributions of the two-zone gridworld (see the module docstring), as a
    :class:`~spoil_torchrl.tabular.problems.DualDemoProblem` with K = 2: ``d_S`` and ``pi_S`` ``[2, S, A]`` (kind
    A, kind B), ``costs`` ``[2, S, A]``, ``mdp`` the CMDP with the maximum of the two costs.

    Args:
        world: from :func:`make_two_zone_gridworld`.
        safeness: share of d_P from the expert optimal under both costs (the rest split equally among the experts
            optimal with no cost, cost A only and cost B only).
        performance: share of each d_S^k from experts that respect kind k (the rest from the careful random
            policy that avoids kind-k zones).
        noise: probability that a d_P expert takes a uniform action instead of its own.
        shared: share of those experts that is the both-kinds one (the rest is the kind-k one).

    Raises:
        ValueError: a share outside [0, 1].

    Examples:
        >>> problem = two_zone_problem(make_two_zone_gridworld(0))
        >>> problem.d_S.shape, [float((d * c).sum()) for d, c in zip(problem.d_S, problem.costs)]
        ((2, 50, 4), [0.0, 0.0])
        >>> [bool((d * c).sum() > 0) for d, c in zip(problem.d_S, problem.costs[::-1])]  # each crosses the other
        [True, True]
    """
    shares = {"safeness": safeness, "performance": performance, "noise": noise, "shared": shared}
    for name, value in shares.items():
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"{name} must lie in [0, 1], got {value}")
    mdp = world.mdp
    kinds = [world.kind(k) for k in range(len(KINDS))]
    experts = expert_policies(world)
    uniform = uniform_policy(mdp)
    noisy = {name: occupancy(mdp, (1.0 - noise) * pi + noise * uniform) for name, pi in experts.items()}
    d_P = (1.0 - safeness) / 3.0 * (noisy["none"] + noisy["A"] + noisy["B"]) + safeness * noisy["both"]
    d_S = np.stack(
        [
            safe_distribution(
                (1.0 - shared) * occupancy(mdp, experts[name]) + shared * occupancy(mdp, experts["both"]),
                occupancy(mdp, safe_random_policy(kind)),
                performance,
            )
            for name, kind in zip(KINDS, kinds, strict=True)
        ]
    )
    d_U = (d_P + d_S.sum(axis=0) + occupancy(mdp, uniform)) / 4.0
    pi_S = np.stack([policy_from_occupancy(d) for d in d_S])
    return DualDemoProblem(mdp, d_P, d_S, d_U, policy_from_occupancy(d_P), pi_S, costs=world.costs.copy())
