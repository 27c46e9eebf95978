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

:func:`explain` turns them into sentences; :func:`explain_run` does so for a run directory. On the command
line:

    python -m spoil_torchrl.eval.dice_diagnostics RUN_DIR [RUN_DIR ...]

explains each run directory named, and each run under a folder of runs (``docs/results/mixed``). A run that
cannot be explained (no ``results.json``, an unreadable one, a run that failed or stopped before its first
evaluation, a method that is not a DICE method) gets one ``error: <run>: <why>`` line on stderr and the others
go on; in a folder of runs, the finished runs of methods without DICE weights (BC, FBC, ...) get a
``skipped <run>: ...`` line instead, as they are expected there. Exit status: 0 when every run was explained
(or skipped so), 1 when one could not be, or none was found to explain, 2 without an argument (the usage).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from tensordict import TensorDict

from spoil_torchrl.objectives.functional import bellman_backup, effective_sample_size

#: Transitions of the DICE role the diagnostics are computed on (a fixed, seeded subsample).
DEFAULT_SAMPLE = 10_000
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
        "kept_by_group": {
            name: float(inside[mask.reshape(-1)].double().mean()) if bool(mask.any()) else 0.0
            for name, mask in (groups or {}).items()
        },
    }


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
        support = data.get("safe_support")
        if support.shape[-1] > 1:  # several constraints: the intersection
            support = support.prod(-1, keepdim=True)
        out["support"] = support_accuracy(support, cost, source_masks(data.get("episode"), pools))
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


def _pct(x: float) -> str:
    return f"{100 * x:.0f} %"


def explain(diag: Mapping, performant_support: Mapping | None = None) -> str:
    """Sentences a researcher can read, from :func:`dice_diagnostics` (and :func:`support_accuracy` of D_P).

    Examples:
        >>> print(explain({"role": "unlabeled", "spread": {"nu": 0.04, "bellman": 0.06, "advantage": 1.0},
        ...     "variance_share": {"bellman": 0.02, "reward": 0.98},
        ...     "weight_share": {"cost>0": {"weight": 0.3, "transitions": 0.2}}, "effective_sample_size": 0.5}))
        ... # doctest: +NORMALIZE_WHITESPACE
        nu's Bellman term gamma*nu(s') - nu(s) explains 2 % of the variance of the advantage (reward 98 %);
        its spread on unlabeled is 0.06 against 1 for the whole advantage.
        nu is nearly flat (its term moves the weights by less than about 10 %): the weights are those of
        weighted BC on the reward term, with no look-ahead.
        30 % of the weight mass sits on transitions with true cost > 0 (they are 20 % of unlabeled):
        the weights favour costly transitions.
        The effective sample size of the weights is 50 % of the transitions.
    """
    share, spread, weight = diag["variance_share"], diag["spread"], diag["weight_share"]
    others = ", ".join(
        f"{k.replace('_', ' ')} {_pct(v)}" for k, v in share.items() if k not in ("bellman", "rest")
    )
    lines = [
        f"nu's Bellman term gamma*nu(s') - nu(s) explains {_pct(share['bellman'])} of the variance of the "
        f"advantage ({others}); its spread on {diag['role']} is {spread['bellman']:.2g} against "
        f"{spread['advantage']:.2g} for the whole advantage."
    ]
    inside = diag.get("variance_share_in_support")
    if inside:
        lines.append(
            f"Inside the estimated support (where lambda * 1_S is constant) nu's term explains "
            f"{_pct(inside['bellman'])} of it and log r_P {_pct(inside['log_ratio_performant'])}."
        )
    if spread["bellman"] < FLAT_SPREAD:
        lines.append(
            "nu is nearly flat (its term moves the weights by less than about 10 %): the weights are those of "
            "weighted BC on the reward term, with no look-ahead."
        )
    costly = weight["cost>0"]
    if abs(costly["weight"] - costly["transitions"]) < 0.01:
        verdict = "the weights neither favour nor avoid costly transitions"
    elif costly["weight"] > costly["transitions"]:
        verdict = "the weights favour costly transitions"
    else:
        verdict = "the weights move mass away from costly transitions"
    lines.append(
        f"{_pct(costly['weight'])} of the weight mass sits on transitions with true cost > 0 (they are "
        f"{_pct(costly['transitions'])} of {diag['role']}): {verdict}."
    )
    sources = sorted(((k, v) for k, v in weight.items() if k != "cost>0"), key=lambda kv: -kv[1]["weight"])
    if sources:
        top = ", ".join(
            f"{k} {_pct(v['weight'])} ({_pct(v['transitions'])} of the data)" for k, v in sources[:4]
        )
        lines.append(f"Weight by source: {top}.")
    if "support" in diag:
        s = diag["support"]
        lines.append(
            f"The support estimate keeps {_pct(s['kept'])} of {diag['role']}; {_pct(s['costly_among_kept'])} of the "
            f"kept transitions have cost > 0, and it lets in {_pct(s['costly_kept'])} of the costly ones."
        )
    if performant_support is not None:
        lines.append(f"It keeps {_pct(performant_support['kept'])} of D_P's transitions.")
    lines.append(
        f"The effective sample size of the weights is {_pct(diag['effective_sample_size'])} of the transitions."
    )
    return "\n".join(lines)


class NotADiceRun(ValueError):
    """A finished run without DICE diagnostics: its method does not weight by DICE (BC, FBC, ...)."""


def _read_results(run_dir: Path) -> dict:
    path = run_dir / "results.json"
    try:
        results = json.loads(path.read_text())
    except OSError as err:
        raise ValueError(f"{run_dir}: results.json cannot be read ({err.strerror})") from None
    except ValueError as err:
        raise ValueError(f"{run_dir}: results.json is unreadable ({err})") from None
    if not isinstance(results, dict):
        raise ValueError(
            f"{run_dir}: results.json holds a JSON {type(results).__name__}, not a run's results"
        )
    return results


def explain_run(run_dir: str | Path) -> str:
    """:func:`explain` for the final diagnostics stored in a run directory's ``results.json``.

    Raises:
        FileNotFoundError: ``run_dir`` has no ``results.json``.
        NotADiceRun: the run finished, and its method is not a DICE method.
        ValueError: ``results.json`` is unreadable or not a run's results, the run stopped before its first
            evaluation (its status and error are named), or its ``dice_diagnostics`` are incomplete.
    """
    run_dir = Path(run_dir)
    if not run_dir.exists():
        raise FileNotFoundError(f"{run_dir}: no such folder")
    if not (run_dir / "results.json").is_file():
        raise FileNotFoundError(
            f"{run_dir}: no results.json (not a run directory of recipes/spoildice_dsrl.py)"
        )
    results = _read_results(run_dir)
    diag = results.get("dice_diagnostics")
    if diag is None:
        status, algo = results.get("status"), results.get("algo")
        if status == "finished":
            raise NotADiceRun(f"{run_dir}: no dice_diagnostics ({algo} is not a DICE method)")
        state = "no status" if status is None else f"status {status}"
        if results.get("error"):
            state += f": {results['error']}"
        raise ValueError(
            f"{run_dir}: no dice_diagnostics ({algo} is not a DICE method, or the run did not reach its "
            f"first evaluation; {state})"
        )
    try:
        return explain(diag, results.get("performant_support"))
    except (AttributeError, KeyError, TypeError, ValueError) as err:
        raise ValueError(
            f"{run_dir}: its dice_diagnostics are incomplete or malformed ({type(err).__name__}: {err})"
        ) from None


def _run_dirs(arg: str) -> tuple[list[Path], bool]:
    """The run directories an argument names (itself, or every run under a folder of runs), and whether it
    is a folder of runs."""
    path = Path(arg)
    if path.is_file() and path.name == "results.json":
        return [path.parent], False
    if not path.is_dir() or (path / "results.json").exists():
        return [path], False
    return sorted({found.parent for found in path.rglob("results.json")}), True


def main(argv: Sequence[str] | None = None) -> int:
    """The command line (see the module's docstring); returns the exit status."""
    import argparse

    parser = argparse.ArgumentParser(
        prog="python -m spoil_torchrl.eval.dice_diagnostics",
        description="Explain the DICE weights of finished runs of recipes/spoildice_dsrl.py.",
    )
    parser.add_argument(
        "runs", nargs="+", metavar="RUN_DIR", help="a run directory, or a folder of runs (each is explained)"
    )
    args = parser.parse_args(argv)
    explained, failed = 0, 0
    for arg in args.runs:
        run_dirs, folder = _run_dirs(arg)
        if not run_dirs:
            print(f"error: {arg}: no results.json in it or under it (not a run directory)", file=sys.stderr)
            failed += 1
        for run_dir in run_dirs:
            try:
                text = explain_run(run_dir)
            except NotADiceRun as err:
                if folder:  # a folder's BC, FBC, ... runs: nothing to explain
                    print(f"skipped {err}", file=sys.stderr)
                    continue
                print(f"error: {err}", file=sys.stderr)
                failed += 1
            except (OSError, ValueError) as err:  # FileNotFoundError included
                print(f"error: {err}", file=sys.stderr)
                failed += 1
            else:
                print(f"{run_dir}:\n{text}\n")
                explained += 1
    if not explained and not failed:
        print("error: no DICE run to explain among " + ", ".join(args.runs), file=sys.stderr)
    return 1 if failed or not explained else 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
