"""The constrained gridworld of section 5.1 / appendix E.1 and its demonstration distributions.

Cells are numbered ``row * size + col`` (row 0 at the top), the absorbing state is ``size * size``; actions are
``0 = up, 1 = down, 2 = left, 3 = right``. Stated by appendix E.1: 11 x 11 cells plus the absorbing state
(122 states), 4 actions, the chosen move with probability 0.99 and each of the 3 other directions with
probability 0.01 / 3, reward 1 at the goal, cost 1 for entering a 3 x 3 constraint zone, zones placed at random
along the main diagonal per seed, gamma = 0.95, delta_c = 1e-4.

Readings where the paper is silent (Figure 3a is not available as text):

- **Layout** (``layout=``, see :data:`LAYOUTS`): section 5.1 asks for a trade-off, "navigate from the start to
  the goal as quickly as possible while avoiding 3 x 3 unsafe zones arranged along the main diagonal", so
  every cost-free route should be longer than the shortest route (so lower return at gamma = 0.95). A
  shortest route is monotone (it never moves away from the goal), and a 4-connected route from one side of
  the main diagonal to the other must step on a diagonal cell ``(k, k)``; zones centred on the diagonal
  therefore block every shortest route only if start and goal lie on *opposite* sides of it and every
  diagonal cell of the rectangle they span is covered.

  - ``"across"`` (the default): start ``(size // 2, 0)`` and goal ``(size // 2, size - 1)``, the middles of
    the left and right edges, and 4 zones. The unique shortest route is the middle row (10 moves), which
    crosses the diagonal at the centre cell; a route that crosses at ``(k, k)`` takes
    ``size - 1 + 2 |k - size // 2|`` moves. The route along the middle row is blocked whenever a zone is
    centred at ``k = 4, 5`` or ``6``, which 4 zones drawn from ``2 .. 8`` miss only in 1 layout of 35
    (``{2, 3, 7, 8}``; in none of seeds 0 .. 49); the cost-free detour is then 2 .. 10 moves longer (via the
    nearest uncovered diagonal cell, at worst round a corner of the grid, which no zone covers), so the CMDP
    optimum's return is 0.60 .. 0.91 of the MDP optimum's (mean 0.71 over seeds 0 .. 49).
  - ``"along"`` (the layout before): start ``(0, 0)`` and goal ``(size - 1, size - 1)``, the two ends of the
    main diagonal, and 3 zones. The zones lie on the diagonal route, but the routes along the grid's edges are
    as short and never touch a zone, so d*_M and d*_Mc have (almost) the same return and d*_M is itself
    feasible in some seeds: no return/safety trade-off.

- **Zones**: ``n_zones`` 3 x 3 zones whose centres are distinct diagonal cells ``(k, k)`` drawn uniformly
  (``np.random.default_rng(seed)``) from the ``k`` whose zone covers no corner of the grid, nor start nor goal
  (``k = 2 .. size-3``, :func:`zone_candidates`); zones may touch or overlap. Keeping the corners free keeps a
  cost-free route (round the grid's edge) in every layout, so the CMDP optimum always reaches the goal.
- **Walls** keep the agent in place (a move off the grid leaves the cell unchanged).
- **Reward**: ``r(goal, a) = 1`` for every action; the goal then leads to the absorbing state with
  probability 1 (whatever the action), and the absorbing state stays absorbing with ``r = c = 0``.
- **Cost**: "entering" is crossing a zone's boundary from outside. By default (``cost_model="crossing"``) the
  *chosen* move is charged and slips are not, because appendix E.1 asks the o = 0 demonstrator, a random
  policy, to be cost-satisfying, which no random-like policy is when slips next to a zone are charged
  (``cost_model="transition"``; see :func:`zone_cost`).
- **Demonstrations**: d_P and d_S are the mixtures of :func:`performant_distribution` and
  :func:`safe_distribution`; the o = 0 behaviour is :func:`safe_random_policy`.

:func:`route_lengths` gives the shortest and the shortest cost-free number of moves of a layout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spoil_torchrl.tabular.cmdp import TabularCMDP, occupancy
from spoil_torchrl.tabular.optimal import solve_cmdp_optimum, solve_mdp_optimum

#: ``(d_row, d_col)`` of the actions up, down, left, right.
MOVES = np.array([[-1, 0], [1, 0], [0, -1], [0, 1]])
ACTION_NAMES = ("up", "down", "left", "right")


@dataclass(frozen=True)
class Gridworld:
    """A constrained gridworld: its CMDP plus the layout needed to draw and reason about it."""

    mdp: TabularCMDP
    size: int
    start: tuple[int, int]
    goal: tuple[int, int]
    zone_centers: tuple[int, ...]  # diagonal indices k of the zones' centre cells (k, k)
    zone: np.ndarray  # [S] bool, True on zone cells (never the absorbing state)
    cost_limit: float  # delta_c

    @property
    def absorbing(self) -> int:
        return self.size * self.size

    def cell(self, row: int, col: int) -> int:
        return row * self.size + col


def zone_cells(size: int, centers) -> np.ndarray:
    """Boolean mask ``[size*size + 1]`` of the cells covered by 3 x 3 zones centred at ``(k, k)`` for ``k`` in
    ``centers`` (the absorbing state is never in a zone).

    Examples:
        >>> zone_cells(4, [1]).reshape(-1)[:16].reshape(4, 4).astype(int).tolist()
        [[1, 1, 1, 0], [1, 1, 1, 0], [1, 1, 1, 0], [0, 0, 0, 0]]
    """
    mask = np.zeros((size, size), dtype=bool)
    for k in centers:
        if not 0 <= k < size:
            raise ValueError(f"zone centre {k} lies outside the {size} x {size} grid")
        mask[max(k - 1, 0) : k + 2, max(k - 1, 0) : k + 2] = True
    return np.append(mask.ravel(), False)


def grid_transition(size: int, goal: tuple[int, int], slip: float) -> np.ndarray:
    """``T[s, a, s']`` of the gridworld: the chosen move w.p. ``1 - slip``, each other direction w.p.
    ``slip / 3``; moves off the grid stay put; the goal and the absorbing state lead to the absorbing state.

    Examples:
        >>> T = grid_transition(2, goal=(1, 1), slip=0.03)
        >>> T[0, 3].round(3).tolist()  # from the top-left cell, "right": 0.97 right, 0.01 down, 0.02 stay
        [0.02, 0.97, 0.01, 0.0, 0.0]
    """
    if not 0.0 <= slip < 0.75:
        raise ValueError(
            f"slip must lie in [0, 0.75), got {slip}: beyond that the chosen move is no longer the most likely "
            "one and the move-based cost and demonstrators would be wrong"
        )
    n_cells = size * size
    absorbing = n_cells
    transition = np.zeros((n_cells + 1, 4, n_cells + 1))
    for row in range(size):
        for col in range(size):
            s = row * size + col
            for a in range(4):
                for direction, (dr, dc) in enumerate(MOVES):
                    p = 1.0 - slip if direction == a else slip / 3.0
                    r, c = row + dr, col + dc
                    target = r * size + c if 0 <= r < size and 0 <= c < size else s
                    transition[s, a, target] += p
    goal_cell = goal[0] * size + goal[1]
    transition[goal_cell] = 0.0
    transition[goal_cell, :, absorbing] = 1.0
    transition[absorbing, :, absorbing] = 1.0
    return transition


COST_MODELS = ("crossing", "transition")


def zone_cost(transition: np.ndarray, zone: np.ndarray, cost_model: str = "crossing") -> np.ndarray:
    """The cost ``c[s, a]`` of *entering* a zone (crossing its boundary from outside), under one of two readings
    of appendix E.1; moves inside a zone cost nothing in both:

    - ``"crossing"``: 1 when ``s`` is outside every zone and the *chosen* move targets a zone cell (the most
      likely next cell of ``(s, a)``); slips are not charged. Careful behaviour then has exactly zero cost, as
      appendix E.1 requires of the o = 0 demonstrator ("a cost-satisfying policy ... o = 0 a random policy").
    - ``"transition"``: the expected cost of actually crossing, slips included:
      ``c(s, a) = 1[s outside zones] * sum_{s' in zone} T(s' | s, a)``; next to a zone every action then costs
      at least ``slip / 3``.

    Examples:
        >>> T = grid_transition(3, goal=(2, 2), slip=0.03)
        >>> zone = np.zeros(10, dtype=bool); zone[1] = True  # the cell (0, 1)
        >>> zone_cost(T, zone, "crossing")[0].tolist(), zone_cost(T, zone, "transition")[0].round(3).tolist()
        ([0.0, 0.0, 0.0, 1.0], [0.01, 0.01, 0.01, 0.97])
        >>> zone_cost(T, zone, "crossing")[1].tolist()  # inside the zone nothing is charged
        [0.0, 0.0, 0.0, 0.0]
    """
    outside = ~zone[:, None]
    if cost_model == "crossing":
        return (zone[transition.argmax(-1)] & outside).astype(np.float64)
    if cost_model == "transition":
        return transition[:, :, zone].sum(-1) * outside
    raise ValueError(f"cost_model must be one of {COST_MODELS}, got {cost_model!r}")


#: The layouts of :func:`make_gridworld`: ``name -> (start, goal, default number of zones)`` for a grid of
#: ``size`` cells a side (see the module docstring).
LAYOUTS = {
    "across": lambda size: ((size // 2, 0), (size // 2, size - 1), 4),
    "along": lambda size: ((0, 0), (size - 1, size - 1), 3),
}


def zone_candidates(size: int, start: tuple[int, int], goal: tuple[int, int]) -> list[int]:
    """The diagonal indices ``k`` a zone centred at ``(k, k)`` may take: those whose 3 x 3 zone covers no corner
    of the grid, nor the start or the goal (``k = 2 .. size - 3`` for both layouts of :data:`LAYOUTS`).

    Examples:
        >>> zone_candidates(11, (5, 0), (5, 10))
        [2, 3, 4, 5, 6, 7, 8]
    """
    keep = [(0, 0), (0, size - 1), (size - 1, 0), (size - 1, size - 1), tuple(start), tuple(goal)]
    cells = [r * size + c for r, c in keep]
    return [k for k in range(size) if not zone_cells(size, [k])[cells].any()]


def make_gridworld(
    seed: int,
    *,
    size: int = 11,
    layout: str = "across",
    n_zones: int | None = None,
    start: tuple[int, int] | None = None,
    goal: tuple[int, int] | None = None,
    slip: float = 0.01,
    gamma: float = 0.95,
    cost_limit: float = 1e-4,
    cost_model: str = "crossing",
) -> Gridworld:
    """The appendix-E.1 gridworld for one seed (zone centres from ``np.random.default_rng(seed)``).

    ``layout`` (a key of :data:`LAYOUTS`) gives the start, the goal and the number of zones wherever
    ``start``, ``goal`` or ``n_zones`` is ``None``. Zone centres are ``n_zones`` distinct draws from
    :func:`zone_candidates`. Defaults are the paper's values and the readings listed in the module docstring.

    Examples:
        >>> grid = make_gridworld(0)
        >>> grid.mdp.n_states, grid.mdp.n_actions, grid.mdp.gamma, grid.cost_limit
        (122, 4, 0.95, 0.0001)
        >>> grid.start, grid.goal, len(grid.zone_centers)
        ((5, 0), (5, 10), 4)
        >>> make_gridworld(0, layout="along").start, make_gridworld(0, layout="along").zone_centers
        ((0, 0), (5, 6, 8))
    """
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {tuple(LAYOUTS)}, got {layout!r}")
    default_start, default_goal, default_zones = LAYOUTS[layout](size)
    start = default_start if start is None else tuple(start)
    goal = default_goal if goal is None else tuple(goal)
    n_zones = default_zones if n_zones is None else int(n_zones)
    for name, (r, c) in (("start", start), ("goal", goal)):
        if not (0 <= r < size and 0 <= c < size):
            raise ValueError(f"{name} {(r, c)} lies outside the {size} x {size} grid")
    if start == goal:
        raise ValueError("start and goal must differ")
    rng = np.random.default_rng(seed)
    candidates = zone_candidates(size, start, goal)
    if not 0 <= n_zones <= len(candidates):
        raise ValueError(f"n_zones must lie in [0, {len(candidates)}] for this grid, got {n_zones}")
    centers = tuple(sorted(int(k) for k in rng.choice(candidates, size=n_zones, replace=False)))
    zone = zone_cells(size, centers)
    transition = grid_transition(size, goal, slip)
    n_states = size * size + 1
    reward = np.zeros((n_states, 4))
    reward[goal[0] * size + goal[1]] = 1.0
    cost = zone_cost(transition, zone, cost_model)
    init = np.zeros(n_states)
    init[start[0] * size + start[1]] = 1.0
    mdp = TabularCMDP(transition, reward, cost, init, gamma)
    return Gridworld(mdp, size, start, goal, centers, zone, float(cost_limit))


def route_lengths(grid: Gridworld) -> tuple[int, int | None]:
    """The number of moves of the shortest route from start to goal, and of the shortest *cost-free* one (no
    move from outside the zones into a zone cell), both without slips; ``None`` when no cost-free route
    exists. Breadth-first search over the grid's cells.

    Examples:
        >>> route_lengths(make_gridworld(0, layout="along"))  # the edge route is as short as the diagonal one
        (20, 20)
        >>> grid = make_gridworld(0)  # zones cover the diagonal cells 2 .. 8: cross at (1, 1) instead of (5, 5)
        >>> grid.zone_centers, route_lengths(grid)
        ((3, 5, 6, 7), (10, 18))
    """
    size = grid.size

    def bfs(safe: bool) -> int | None:
        start, goal = grid.cell(*grid.start), grid.cell(*grid.goal)
        dist = {start: 0}
        frontier = [start]
        while frontier:
            nxt = []
            for s in frontier:
                if s == goal:
                    return dist[s]
                row, col = divmod(s, size)
                for dr, dc in MOVES:
                    r, c = row + dr, col + dc
                    if not (0 <= r < size and 0 <= c < size):
                        continue
                    t = r * size + c
                    if t in dist or (safe and grid.zone[t] and not grid.zone[s]):
                        continue
                    dist[t] = dist[s] + 1
                    nxt.append(t)
            frontier = nxt
        return None

    return bfs(False), bfs(True)


def safe_random_policy(grid: Gridworld) -> np.ndarray:
    """The o = 0 behaviour of :func:`safe_distribution`: uniform over the actions whose *intended* move does
    not enter a zone cell (moves into a wall count as staying). Where every move enters a zone (the centre of
    a zone, reached only by slipping), uniform over all actions.

    It avoids zones on purpose but still slips into them with probability 0.01 / 3 per neighbouring zone cell,
    so its expected cost need not be below delta_c (the recipe reports it).

    Examples:
        >>> grid = make_gridworld(0, size=5, n_zones=1)
        >>> grid.zone_centers, safe_random_policy(grid)[grid.cell(0, 3)].round(3).tolist()  # zone at (1..3)^2
        ((2,), [0.333, 0.0, 0.333, 0.333])
    """
    intended = grid.mdp.transition.argmax(-1)  # the chosen move has probability 1 - slip > slip / 3
    allowed = ~grid.zone[intended]
    allowed[~allowed.any(axis=1)] = True
    return allowed / allowed.sum(axis=1, keepdims=True)


def uniform_policy(mdp: TabularCMDP) -> np.ndarray:
    """The uniform random policy, the 0 of the normalised return (appendix E.2, Figure A).

    Examples:
        >>> uniform_policy(make_gridworld(0).mdp)[0].tolist()
        [0.25, 0.25, 0.25, 0.25]
    """
    return np.full((mdp.n_states, mdp.n_actions), 1.0 / mdp.n_actions)


def _check_level(value: float, name: str) -> float:
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"{name} must lie in [0, 1], got {value}")
    return float(value)


def performant_distribution(d_mdp, d_cmdp, safeness: float) -> np.ndarray:
    """Appendix E.1: :math:`d_P = (1-\\xi) d^*_M + \\xi d^*_{M_c}` with :math:`\\xi` = ``safeness`` of d_P
    (Figure 3b's labels: the share of CMDP-optimal demonstrations in D_P).

    Examples:
        >>> performant_distribution(np.array([[1.0, 0.0]]), np.array([[0.0, 1.0]]), 0.3).tolist()
        [[0.7, 0.3]]
    """
    xi = _check_level(safeness, "safeness")
    return (1.0 - xi) * np.asarray(d_mdp, dtype=np.float64) + xi * np.asarray(d_cmdp, dtype=np.float64)


def safe_distribution(d_cmdp, d_random, performance: float) -> np.ndarray:
    """Appendix E.1's :math:`d^o_{M_c}`, read as :math:`d_S = o\\, d^*_{M_c} + (1-o)\\, d_0` with :math:`o` =
    ``performance`` of d_S (Figure 3b's labels: the share of high-quality, CMDP-optimal demonstrations in D_S)
    and :math:`d_0` the occupancy of :func:`safe_random_policy`. A mixture of occupancies is the occupancy of
    a mixture of demonstrators, so D_S is o parts CMDP-optimal and 1 - o parts random-but-careful trajectories.

    Examples:
        >>> safe_distribution(np.array([[1.0, 0.0]]), np.array([[0.5, 0.5]]), 0.5).tolist()
        [[0.75, 0.25]]
    """
    o = _check_level(performance, "performance")
    return o * np.asarray(d_cmdp, dtype=np.float64) + (1.0 - o) * np.asarray(d_random, dtype=np.float64)


@dataclass(frozen=True)
class Demonstrators:
    """The occupancies appendix E.1 builds the demonstrations from, and the two ends of the return scale."""

    d_mdp: np.ndarray  # d*_M, the unconstrained optimum
    d_cmdp: np.ndarray  # d*_Mc, the CMDP optimum (E_d[c] <= delta_c)
    d_random: np.ndarray  # d_0, the occupancy of safe_random_policy
    random_return: float  # J(uniform policy; r), the 0 of the normalised return
    optimal_return: float  # J(d*_Mc; r), the 1 of the normalised return


def make_demonstrators(grid: Gridworld) -> Demonstrators:
    """Solve the gridworld's MDP and CMDP optima by linear programming and evaluate the reference policies.

    Examples:
        >>> demo = make_demonstrators(make_gridworld(0))
        >>> bool(demo.optimal_return > demo.random_return)
        True
    """
    mdp = grid.mdp
    d_mdp = solve_mdp_optimum(mdp)
    d_cmdp = solve_cmdp_optimum(mdp, grid.cost_limit)
    d_random = occupancy(mdp, safe_random_policy(grid))
    random_return = float((occupancy(mdp, uniform_policy(mdp)) * mdp.reward).sum())
    return Demonstrators(d_mdp, d_cmdp, d_random, random_return, float((d_cmdp * mdp.reward).sum()))
