"""Why a DICE run behaves as it does: what its weights are made of, where their mass falls, and how good the
safe-support estimate is, measured against the dataset's *true* cost (which training never reads).

Three groups of numbers, all on one fixed subsample of the DICE role's transitions (D_U for SpoilDICE):

* **Spread and variance shares** of the advantage :math:`A` (the exponent of the weights, written by every DICE
  loss at ``dice_advantage``): the Bellman term :math:`b = \\gamma\\nu(s')(1-d) - \\nu(s)` against the rest
  (SpoilDICE: :math:`\\log\\hat r_P` and :math:`\\lambda\\hat{\\mathbb 1}_S`). Share of a term :math:`t` is
  :math:`\\mathrm{cov}(t, A) / \\mathrm{var}(A)` (:func:`variance_shares`); the shares of terms adding up to
  :math:`A` sum to 1. A Bellman share near 0 means :math:`\\nu` is flat and the method is weighted BC.
* **Weight mass** (self-normalised weights) per source of the data (the policy that made each episode, from a
  generated dataset's metadata) and on transitions with true cost > 0, next to each group's share of the
  transitions (:func:`weight_shares`).
* **Support against the truth** (:func:`support_accuracy`): among transitions inside :math:`\\hat{\\mathbb 1}_S`,
  the share with cost > 0; the share of cost > 0 transitions let in; the share kept per source and of D_P.

The sentences that explain them, and the command line that prints them for finished runs
(``python -m spoil_torchrl.eval.dice_explain RUN_DIR ...``), are in
:mod:`~spoil_torchrl.eval.dice_explain`.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from tensordict import TensorDict

from spoil_torchrl.data.constraint_costs import constraint_names
from spoil_torchrl.data.episodes import CONSTRAINTS_KEY
from spoil_torchrl.objectives.functional import bellman_backup, effective_sample_size

#: Transitions of the DICE role the diagnostics are computed on (a fixed, seeded subsample).
DEFAULT_SAMPLE = 10_000
#: The row of :func:`support_by_constraint` for the whole support (no constraint may take this name).
ALL_CUTS = "all"
#: A Bellman term whose standard deviation is below this (in nats) moves the weights by less than ~10 %.
FLAT_SPREAD = 0.1


def _std(x: torch.Tensor) -> float:
    return float(x.double().std(unbiased=False))


def variance_shares(total: torch.Tensor, terms: Mapping[str, torch.Tensor]) -> dict[str, float]:
    """``cov(term, total) / var(total)`` for each term: how much of ``total``'s variance each term carries.

    When the terms add up to ``total`` (up to a constant) the shares sum to 1; a term that varies but is
    cancelled by another can have a negative share. ``var(total) = 0`` gives 0 for every term.

    Examples:
        >>> a, b = torch.tensor([0.0, 1.0, 2.0, 3.0]), torch.tensor([0.0, 0.0, 0.1, 0.0])
        >>> {k: round(v, 3) for k, v in variance_shares(a + b, {"a": a, "b": b}).items()}
        {'a': 0.989, 'b': 0.011}
    """
    total = total.double().reshape(-1)
    centered = total - total.mean()
    var = centered.pow(2).mean()
    if float(var) == 0.0:
        return {name: 0.0 for name in terms}
    return {
        name: float(((t.double().reshape(-1) - t.double().mean()) * centered).mean() / var)
        for name, t in terms.items()
    }


def weight_shares(weights: torch.Tensor, groups: Mapping[str, torch.Tensor]) -> dict[str, dict[str, float]]:
    """For each boolean mask of ``groups``: the share of the weight mass on it and its share of transitions.

    Examples:
        >>> w = torch.tensor([3.0, 1.0, 0.0, 0.0])
        >>> weight_shares(w, {"first": torch.tensor([True, False, False, False])})
        {'first': {'weight': 0.75, 'transitions': 0.25}}
    """
    weights = weights.double().reshape(-1)
    mass = float(weights.sum())
    return {
        name: {
            "weight": float(weights[mask.reshape(-1)].sum()) / mass if mass > 0 else 0.0,
            "transitions": float(mask.double().mean()),
        }
        for name, mask in groups.items()
    }


def _share_kept(inside: torch.Tensor, of: torch.Tensor) -> float:
    """The share of the transitions of mask ``of`` that mask ``inside`` keeps (0 when ``of`` is empty)."""
    of = of.reshape(-1)
    return float(inside.reshape(-1)[of].double().mean()) if bool(of.any()) else 0.0


def support_accuracy(
    support: torch.Tensor, cost: torch.Tensor, groups: Mapping[str, torch.Tensor] | None = None
) -> dict:
    """How a 0/1 support estimate :math:`\\hat{\\mathbb 1}_S` agrees with the true per-step cost.

    Returns ``kept`` (share of transitions inside), ``costly_among_kept`` (share of the kept ones with cost > 0),
    ``costly_kept`` (share of cost > 0 transitions let in), ``costly`` (share of cost > 0 transitions) and, per
    mask of ``groups``, the share of its transitions kept (``kept_by_group``).

    Examples:
        >>> s = torch.tensor([1.0, 1.0, 0.0, 1.0])
        >>> c = torch.tensor([0.0, 1.0, 1.0, 0.0])
        >>> support_accuracy(s, c)
        {'kept': 0.75, 'costly_among_kept': 0.3333333333333333, 'costly_kept': 0.5, 'costly': 0.5, 'kept_by_group': {}}
    """
    inside = support.reshape(-1) > 0.5
    costly = cost.reshape(-1) > 0
    n_inside, n_costly = int(inside.sum()), int(costly.sum())
    return {
        "kept": float(inside.double().mean()),
        "costly_among_kept": float((inside & costly).sum()) / n_inside if n_inside else 0.0,
        "costly_kept": float((inside & costly).sum()) / n_costly if n_costly else 0.0,
        "costly": float(costly.double().mean()),
        "kept_by_group": {name: _share_kept(inside, mask) for name, mask in (groups or {}).items()},
    }


def support_by_constraint(data: TensorDict) -> dict | None:
    """The support estimate against each constraint's own true cost (several constraints,
    ``docs/several_constraints.md``).

    ``costly_kept[cut][j]`` is the share of the transitions with cost > 0 on constraint ``j`` that the cut of
    constraint ``cut`` (the annotation ``safe_support_<cut>``) keeps; the row ``"all"`` is the whole support
    ``safe_support`` (the intersection of the cuts, or the one cut of a merged safe set). ``costly[j]`` is the
    share of transitions with cost > 0 on ``j``. A cut that tells its constraint apart keeps few of its own
    costly transitions (the diagonal) and those of the other constraints as far as its safe set holds them; a
    cut that keeps both alike cannot tell the constraints apart. A constraint with no costly transition gets 0
    in every row (``costly[j] == 0`` tells it from a cut that rejects them all). ``None`` when ``data`` carry no
    support or no per-constraint costs (``("next", "constraint_costs", <name>)``).

    Examples:
        >>> a, b = torch.tensor([[0.0], [1.0], [1.0], [0.0]]), torch.tensor([[1.0], [0.0], [1.0], [1.0]])
        >>> data = TensorDict({"safe_support_a": a, "safe_support_b": b, "safe_support": torch.cat([a, b], -1),
        ...     "next": {"constraint_costs": {"a": torch.tensor([[1.0], [0.0], [0.0], [0.0]]),
        ...                                   "b": torch.tensor([[0.0], [1.0], [1.0], [1.0]])}}}, [4])
        >>> support_by_constraint(data)  # cut a keeps 2 of the 3 b-costly steps, cut b the a-costly one
        {'costly': {'a': 0.25, 'b': 0.75}, 'costly_kept': {'a': {'a': 0.0, 'b': 0.6666666666666666}, \
'b': {'a': 1.0, 'b': 0.6666666666666666}, 'all': {'a': 0.0, 'b': 0.3333333333333333}}}
    """
    names = constraint_names(data)
    if not names or "safe_support" not in data.keys():
        return None
    costly = {j: data.get(("next", CONSTRAINTS_KEY, j)).reshape(-1) > 0 for j in names}
    cuts = sorted(k.removeprefix("safe_support_") for k in data.keys() if k.startswith("safe_support_"))
    inside = {k: data.get(f"safe_support_{k}").reshape(-1) > 0.5 for k in cuts}
    if ALL_CUTS in inside:
        raise ValueError(f"a constraint named {ALL_CUTS!r}: the name of the whole support's row is taken")
    inside[ALL_CUTS] = data.get("safe_support").prod(-1).reshape(-1) > 0.5
    return {
        "costly": {j: float(costly[j].double().mean()) for j in names},
        "costly_kept": {k: {j: _share_kept(mask, costly[j]) for j in names} for k, mask in inside.items()},
    }


def annotated_support_accuracy(
    data: TensorDict, pools: Mapping[str, torch.Tensor] | None = None, cost_key=("next", "cost")
) -> dict:
    """:func:`support_accuracy` of the support annotated on ``data`` (``safe_support``; with several constraints
    the intersection of its columns) against the true cost at ``cost_key``, per source of ``pools``, and with
    several constraints each cut against each constraint's cost (``by_constraint``, :func:`support_by_constraint`).

    Examples:
        >>> data = TensorDict({"safe_support": torch.tensor([[1.0], [0.0]]), "episode": torch.tensor([0, 1]),
        ...                    "next": {"cost": torch.tensor([[0.0], [1.0]])}}, [2])
        >>> annotated_support_accuracy(data, {"first": torch.tensor([0])})["kept_by_group"]
        {'first': 1.0}
    """
    support = data.get("safe_support").prod(-1, keepdim=True)  # several constraints: the intersection
    out = support_accuracy(support, data.get(cost_key), source_masks(data.get("episode"), pools))
    by_constraint = support_by_constraint(data)
    if by_constraint is not None:
        out["by_constraint"] = by_constraint
    return out


def source_masks(episode: torch.Tensor, pools: Mapping[str, torch.Tensor] | None) -> dict[str, torch.Tensor]:
    """Boolean masks over transitions, one per source (``pools`` maps a label to its episode ids).

    Examples:
        >>> source_masks(torch.tensor([0, 0, 1, 2]), {"a": torch.tensor([0, 2])})["a"].tolist()
        [True, True, False, True]
    """
    episode = episode.reshape(-1)
    return {label: torch.isin(episode, torch.as_tensor(ids)) for label, ids in (pools or {}).items()}


def subsample(data: TensorDict, n: int = DEFAULT_SAMPLE, seed: int = 0) -> TensorDict:
    """At most ``n`` rows of ``data``, drawn without replacement with a fixed seed (all rows if fewer)."""
    if data.shape[0] <= n:
        return data.clone()
    idx = torch.randperm(data.shape[0], generator=torch.Generator().manual_seed(seed))[:n]
    return data[torch.sort(idx).values].clone()


@torch.no_grad()
def dice_diagnostics(
    loss,
    transitions: TensorDict,
    init: TensorDict,
    *,
    role: str,
    pools: Mapping[str, torch.Tensor] | None = None,
    cost_key=("next", "cost"),
) -> dict:
    """All diagnostics of a DICE loss (one with a ``nu_network``, writing ``dice_weight`` and
    ``dice_advantage``) on ``transitions`` of ``role`` and the initial states ``init``.

    The loss is run once on the whole set, so the weights are self-normalised over it (mean 1), without
    touching torch's global random stream (a run with diagnostics trains exactly as one without). ``pools``
    maps source labels to episode ids; the true cost is read at ``cost_key`` for the diagnostics only.

    Examples:
        >>> from spoil_torchrl.modules import make_value_network
        >>> from spoil_torchrl.objectives import SpoilDICELoss
        >>> n = 64
        >>> data = TensorDict({
        ...     "observation": torch.randn(n, 3), "episode": torch.arange(n) // 8,
        ...     "next": {"observation": torch.randn(n, 3), "terminated": torch.zeros(n, 1, dtype=torch.bool),
        ...              "cost": (torch.arange(n) % 2).float().unsqueeze(-1)},
        ...     "log_ratio_performant": torch.randn(n, 1), "safe_support": torch.ones(n, 1)}, [n])
        >>> loss = SpoilDICELoss(make_value_network(3, hidden_cells=(8,)))
        >>> diag = dice_diagnostics(loss, data, TensorDict({"observation": torch.randn(8, 3)}, [8]),
        ...                         role="unlabeled", pools={"even": torch.arange(0, 8, 2)})
        >>> round(sum(diag["variance_share"].values()), 6), diag["weight_share"]["even"]["transitions"]
        (1.0, 0.5)
    """
    data = transitions.clone()
    with torch.random.fork_rng():  # the loss's penalty draws random points: leave the training's stream alone
        loss(TensorDict({role: data, "init": init}, []))
    weights = data.get("dice_weight").reshape(-1).double()
    advantage = data.get("dice_advantage").reshape(-1).double()
    nu_net = loss.get_stateful_net("nu_network", copy=False)
    nu = nu_net(data.select(*nu_net.in_keys).clone()).get(nu_net.out_keys[0]).reshape(-1)
    nxt = data.get("next")
    next_nu = nu_net(nxt.select(*nu_net.in_keys).clone()).get(nu_net.out_keys[0]).reshape(-1)
    terminated = nxt.get("terminated").reshape(-1)
    bellman = (bellman_backup(next_nu, terminated, loss.gamma) - nu).double()

    terms = {"bellman": bellman}
    in_support = None
    spread = {"nu": _std(nu), "bellman": _std(bellman), "advantage": _std(advantage)}
    if "log_ratio_performant" in data.keys() and "safe_support" in data.keys() and hasattr(loss, "lagrange"):
        log_ratio = data.get("log_ratio_performant").reshape(-1).double()
        if loss.lagrange.ndim == 0:
            lam_support = float(loss.lagrange) * data.get("safe_support").reshape(-1).double()
            inside = data.get("safe_support").reshape(-1) > 0.5  # where the weights have their mass
        else:  # several constraints: sum_k lambda_k 1_k, mass inside every support
            support = data.get("safe_support").reshape(-1, loss.lagrange.shape[0]).double()
            lam_support = (support * loss.lagrange.detach().double()).sum(-1)
            inside = support.prod(-1) > 0.5
        terms.update(log_ratio_performant=log_ratio, lagrange_support=lam_support)
        spread.update(log_ratio_performant=_std(log_ratio), lagrange_support=_std(lam_support))
        terms["rest"] = advantage - bellman - log_ratio - lam_support  # ~0 for SpoilDICE (Eq. 7)
        if int(inside.sum()) > 1:
            in_support = {k: v[inside] for k, v in terms.items() if k != "lagrange_support"}
    else:
        terms["reward"] = advantage - bellman
        spread["reward"] = _std(terms["reward"])

    cost = data.get(cost_key).reshape(-1)
    groups = source_masks(data.get("episode"), pools)
    groups["cost>0"] = cost > 0
    out = {
        "role": role,
        "transitions": int(data.shape[0]),
        "spread": spread,
        "variance_share": variance_shares(advantage, terms),
        # SpoilDICE: the same inside the estimated support, where lambda * 1_S is constant
        "variance_share_in_support": None
        if in_support is None
        else variance_shares(advantage[inside], in_support),
        "weight_share": weight_shares(weights, groups),
        "effective_sample_size": float(effective_sample_size(weights)),
    }
    if hasattr(loss, "lagrange"):
        lagrange = loss.lagrange.detach()
        out["lagrange"] = float(lagrange) if lagrange.ndim == 0 else lagrange.tolist()
    if "safe_support" in data.keys():
        out["support"] = annotated_support_accuracy(data, pools, cost_key)
    return out


def summary_scalars(diag: Mapping) -> dict[str, float]:
    """The few numbers worth a learning curve: spreads, the Bellman share, weight on cost > 0.

    Examples:
        >>> summary_scalars({"spread": {"nu": 1.0}, "variance_share": {"bellman": 0.5},
        ...                  "weight_share": {"cost>0": {"weight": 0.1, "transitions": 0.2}}})
        {'dice/spread_nu': 1.0, 'dice/share_bellman': 0.5, 'dice/weight_on_cost': 0.1}
    """
    out = {f"dice/spread_{k}": float(v) for k, v in diag["spread"].items()}
    out.update({f"dice/share_{k}": float(v) for k, v in diag["variance_share"].items()})
    if diag.get("variance_share_in_support"):
        out["dice/share_bellman_in_support"] = float(diag["variance_share_in_support"]["bellman"])
    out["dice/weight_on_cost"] = float(diag["weight_share"]["cost>0"]["weight"])
    return out
