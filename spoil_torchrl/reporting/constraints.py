"""The per-constraint table of a report (several constraints, ``docs/several_constraints.md``): for runs whose
evaluations report each constraint's episode cost (``cost_<name>``) and the share of episodes within every limit
(``feasible_all``), each method's mean over seeds of those, and, where the run's DICE diagnostics set each
support cut against each constraint's own cost (``support.by_constraint``), how much of its own constraint's
costly transitions each cut lets in.

``python recipes/report.py <folders>`` prints it below the main table when such runs are among those reported.
"""

from __future__ import annotations

import torch

from spoil_torchrl.eval import format_mean_stderr, mean_stderr
from spoil_torchrl.eval.figures import ALGORITHM_NAMES, algorithm_order
from spoil_torchrl.runs.results import aggregate

#: The evaluation key of the share of episodes within every constraint's limit.
WITHIN_ALL = "feasible_all"


def _reported(results: dict) -> set[str]:
    """The keys every evaluation of a run's aggregate (its last ``last_evaluations``) reports."""
    evaluations = (results.get("evaluations") or [{}])[-int(results.get("last_evaluations") or 1) :]
    return set.intersection(*(set(e) for e in evaluations))


def constraint_names(results: dict) -> list[str]:
    """The constraints whose episode costs every evaluation of a run's aggregate reports (``[]`` for none).

    Examples:
        >>> constraint_names({"evaluations": [{"cost": 3.0, "cost_x_wall": 1.0, "cost_y_wall": 2.0}]})
        ['x_wall', 'y_wall']
        >>> constraint_names({"evaluations": [{"cost": 3.0}]})
        []
    """
    return sorted(k.removeprefix("cost_") for k in _reported(results) if k.startswith("cost_"))


def _own_leak(group: list[dict], name: str) -> tuple[float, float] | None:
    """Mean and standard error over seeds of the share of D_U's transitions costly on ``name`` that ``name``'s
    own cut lets in (``None`` unless every seed's diagnostics have that cut)."""
    shares = []
    for r in group:
        by = ((r.get("dice_diagnostics") or {}).get("support") or {}).get("by_constraint") or {}
        row = by.get("costly_kept", {}).get(name)
        if row is None or name not in row:
            return None
        shares.append(row[name])
    return mean_stderr(torch.tensor(shares, dtype=torch.float64))


def constraint_markdown(runs: dict[tuple[str, str], list[dict]]) -> str | None:
    """One table per dataset whose runs all report the same constraints (``None`` when no dataset does): raw
    episode cost, each constraint's episode cost, the share of episodes within every limit, and each cut's
    share of its own constraint's costly transitions (mean ± s.e. over seeds of each seed's last evaluations).

    Examples:
        >>> ev = lambda c: {"cost": c, "cost_a": c / 2, "cost_b": c / 2, "feasible_all": float(c < 25)}
        >>> def run(seed, c):
        ...     return {"seed": seed, "last_evaluations": 1, "evaluations": [ev(99.0), ev(c)]}
        >>> text = constraint_markdown({("d", "spoildice"): [run(0, 10.0), run(1, 30.0)]})
        >>> print("\\n".join(text.splitlines()[:5]))  # doctest: +NORMALIZE_WHITESPACE
        **d**, per constraint
        <BLANKLINE>
        | algorithm | seeds | cost | a cost | b cost | episodes within every limit | a cut keeps of a's costly
          | b cut keeps of b's costly |
        |---|---|---|---|---|---|---|---|
        | SpoilDICE | 2 | 20.00 ± 10.00 | 10.00 ± 5.00 | 10.00 ± 5.00 | 0.50 ± 0.50 | - | - |
    """
    lines: list[str] = []
    for dataset in sorted({d for d, _ in runs}):
        algos = sorted((a for d, a in runs if d == dataset), key=algorithm_order)
        names = {tuple(constraint_names(r)) for a in algos for r in runs[(dataset, a)]}
        if len(names) != 1 or not next(iter(names)):
            continue
        names = list(next(iter(names)))
        keys = ["cost", *(f"cost_{n}" for n in names)]
        has_within = all(WITHIN_ALL in _reported(r) for a in algos for r in runs[(dataset, a)])
        keys += [WITHIN_ALL] if has_within else []
        header = ["algorithm", "seeds", "cost", *(f"{n} cost" for n in names)]
        header += ["episodes within every limit"] if has_within else []
        header += [f"{n} cut keeps of {n}'s costly" for n in names]
        lines += [f"**{dataset}**, per constraint", "", "| " + " | ".join(header) + " |"]
        lines.append("|" + "---|" * len(header))
        for algo in algos:
            group = runs[(dataset, algo)]
            per_seed = [aggregate(r["evaluations"], int(r["last_evaluations"]), keys) for r in group]
            cells = [
                format_mean_stderr(*mean_stderr(torch.tensor([s[k] for s in per_seed], dtype=torch.float64)))
                for k in keys
            ]
            for n in names:
                leak = _own_leak(group, n)
                cells.append(
                    "-" if leak is None else f"{format_mean_stderr(100 * leak[0], 100 * leak[1], 1)} %"
                )
            lines.append(f"| {ALGORITHM_NAMES.get(algo, algo)} | {len(group)} | " + " | ".join(cells) + " |")
        lines.append("")
    if not lines:
        return None
    lines.append(
        "Per constraint: raw episode costs (each limit as the dataset's), mean ± standard error over seeds of "
        "each seed's last evaluations; the last columns (SpoilDICE with one cut per constraint): the share of "
        "D_U's transitions over each constraint that its own cut keeps (results.json `dice_diagnostics.support."
        "by_constraint`, on the diagnostics' subsample; '-' where a run does not report it)."
    )
    return "\n".join(lines)
