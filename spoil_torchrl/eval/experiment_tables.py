"""The tables, figure panels and aggregate statistics of a paper experiment, from its cells' results.

An :class:`Experiment` holds the finished cells of one experiment (read from run directories by
:func:`~spoil_torchrl.reporting.experiments.load_experiment`). :func:`level_summary` gives per task, level and method
the mean and standard error over seeds of the normalised feasible return and cost, and :func:`task_average` the
same averaged over the tasks present, as the paper's Fig. 4 averages its six tasks. :func:`experiment_markdown`
writes both as tables, one column per level, :func:`diagnostics_markdown` the DICE diagnostics of the weighted
methods per level, and :func:`experiment_statistics` adds the aggregate statistics of
few-seed results (interquartile mean with stratified-bootstrap intervals over seeds and tasks, the probability
that SpoilDICE improves on each baseline; :mod:`spoil_torchrl.eval.aggregate`). ``spoil-report --figure`` draws
and writes them.

Example:
    >>> cells = {("pc1", 0.5, "bc"): [{"aggregate": {"normalized_feasible_return": 0.4, "normalized_cost": 2.0}},
    ...                               {"aggregate": {"normalized_feasible_return": 0.6, "normalized_cost": 4.0}}]}
    >>> level_summary(cells)[("pc1", 0.5, "bc")]["normalized_cost"]
    (3.0, 1.0)
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import torch

from spoil_torchrl.eval.figures import ALGORITHM_NAMES, algorithm_order
from spoil_torchrl.eval.tables import mean_stderr

#: What the figures and tables show, per seed the mean of its last evaluations (``results.json`` ``aggregate``).
METRICS = ("normalized_feasible_return", "normalized_cost")
METRIC_NAMES = {
    "normalized_feasible_return": "normalised feasible return",
    "normalized_cost": "normalised cost",
}
#: (dataset, level value, algorithm) -> the results of its seeds, sorted by seed.
Cells = dict[tuple[str, object, str], list[dict]]


@dataclass
class Experiment:
    """The finished cells of one experiment: its ``name``, the setting it varies (``level``, ``None`` for a
    table) and ``cells``; ``unfinished`` lists the other cells found (run directory, status);
    ``resumed_elsewhere`` the cells resumed on another machine than the one that started them."""

    name: str
    level: str | None
    cells: Cells = field(default_factory=dict)
    unfinished: list[tuple[str, str]] = field(default_factory=list)
    files: dict[str, dict[str, int]] = field(default_factory=dict)  # dataset -> file fingerprint -> cells
    resumed_elsewhere: list[str] = field(default_factory=list)  # cells whose parts ran on several machines

    @property
    def datasets(self) -> list[str]:
        return sorted({d for d, _, _ in self.cells})

    @property
    def levels(self) -> list:
        return sorted({v for _, v, _ in self.cells}, key=lambda v: (v is None, v))

    @property
    def algos(self) -> list[str]:
        return sorted({a for _, _, a in self.cells}, key=algorithm_order)


def level_summary(cells: Mapping[tuple, list[dict]]) -> dict[tuple, dict]:
    """Per cell (dataset, level, algorithm): ``seeds`` and, per metric, the mean and standard error over seeds
    of the seeds' aggregates (:data:`METRICS`)."""
    out = {}
    for key, group in cells.items():
        row: dict = {"seeds": len(group)}
        for metric in METRICS:
            row[metric] = mean_stderr(
                torch.tensor([r["aggregate"][metric] for r in group], dtype=torch.float64)
            )
        out[key] = row
    return out


def task_average(summary: Mapping[tuple, dict]) -> dict[tuple, dict]:
    """Per (level, algorithm) present on every task: the mean over tasks of the per-task means, and its standard
    error sqrt(sum of the tasks' squared standard errors) / tasks (the tasks' seeds are independent runs).

    Examples:
        >>> s = {("a", 1, "bc"): {"seeds": 2, "normalized_feasible_return": (0.2, 0.3), "normalized_cost": (1.0, 0.0)},
        ...      ("b", 1, "bc"): {"seeds": 2, "normalized_feasible_return": (0.6, 0.4), "normalized_cost": (3.0, 0.0)}}
        >>> task_average(s)[(1, "bc")]["normalized_feasible_return"]
        (0.4, 0.25)
    """
    datasets = sorted({d for d, _, _ in summary})
    out = {}
    for level, algo in sorted({(v, a) for _, v, a in summary}, key=lambda k: (str(k[0]), k[1])):
        rows = [summary.get((d, level, algo)) for d in datasets]
        if any(r is None for r in rows):
            continue
        row: dict = {"tasks": len(rows), "seeds": sum(r["seeds"] for r in rows)}
        for metric in METRICS:
            means = [r[metric][0] for r in rows]
            errors = [r[metric][1] if math.isfinite(r[metric][1]) else float("nan") for r in rows]
            row[metric] = (sum(means) / len(rows), math.sqrt(sum(e * e for e in errors)) / len(rows))
        out[(level, algo)] = row
    return out


def _cell(value: tuple[float, float], bold: bool) -> str:
    mean, se = value
    text = f"{mean:.2f} ± {se:.2f}" if math.isfinite(se) else f"{mean:.2f}"
    return f"**{text}**" if bold else text


def _head(first: str, levels: list, level: str | None) -> list[str]:
    """A table's header and rule: ``first``, then one column per level ("value" for a table of one
    configuration, ``level`` ``None``)."""
    head = [str(v) if level is not None else "value" for v in levels]
    return [f"| {first} | " + " | ".join(head) + " |", "|---" * (len(levels) + 1) + "|"]


def _table(
    rows: Mapping[tuple, dict], levels: list, algos: list[str], metric: str, level: str | None
) -> list[str]:
    lines = _head(METRIC_NAMES[metric], levels, level)
    for algo in algos:
        cells = []
        for value in levels:
            row = rows.get((value, algo))
            cells.append("-" if row is None else _cell(row[metric], row["normalized_cost"][0] <= 1.0))
        lines.append(f"| {ALGORITHM_NAMES.get(algo, algo)} | " + " | ".join(cells) + " |")
    return lines


def figure_panels(experiment: Experiment) -> list[tuple[str, dict]]:
    """``(title, rows)`` per panel of the experiment's tables and figure: the average over tasks (the task's
    name when there is one), then each task; ``rows[(level, algo)]`` as in :func:`task_average`."""
    summary = level_summary(experiment.cells)
    datasets = experiment.datasets
    if len(datasets) == 1:
        return [(datasets[0], task_average(summary))]
    per_task = [(d, {(v, a): r for (dd, v, a), r in summary.items() if dd == d}) for d in datasets]
    return [(f"average over {len(datasets)} tasks", task_average(summary)), *per_task]


def experiment_markdown(experiment: Experiment) -> str:
    """The experiment's numbers as markdown: for the average over tasks and for each task, one table per metric
    with a row per method and a column per level (mean ± s.e. over seeds; safe on average in bold)."""
    levels, algos = experiment.levels, experiment.algos
    what = f"against {experiment.level}" if experiment.level else "one configuration"
    lines = [f"### {experiment.name}: {what}", ""]
    panels = figure_panels(experiment)
    for title, rows in panels:
        lines += [f"**{title}**", ""]
        for metric in METRICS:
            lines += [*_table(rows, levels, algos, metric, experiment.level), ""]
    if experiment.unfinished:  # a failed (diverged) cell is a result too: say which, not only leave it out
        lines += [f"Not finished, so not in the tables ({len(experiment.unfinished)}):", ""]
        lines += [f"- `{where}`: {reason}" for where, reason in experiment.unfinished]
        lines.append("")
    for dataset, counts in sorted(experiment.files.items()):
        if len(counts) > 1:  # said wherever the numbers are read: they mix files of one dataset
            parts = ", ".join(f"`{fingerprint}`: {n} runs" for fingerprint, n in sorted(counts.items()))
            lines += [
                f"{dataset}: the runs were trained on {len(counts)} files of this dataset ({parts}).",
                "",
            ]
    seeds = sorted({len(group) for group in experiment.cells.values()})
    lines.append(
        f"Seeds per cell: {', '.join(map(str, seeds))}. Each seed contributes the mean of its last evaluations; "
        "± is the standard error over seeds (averages over tasks: of the mean of the task means). Bold: safe on "
        "average (normalised cost <= 1)."
    )
    return "\n".join(lines)


#: The DICE diagnostics :func:`diagnostics_markdown` tabulates: (row name, path into ``results.json``'s
#: ``dice_diagnostics``). A row a method's runs do not record is left out of its table.
DIAGNOSTICS = (
    ("support: share of D_U kept", ("support", "kept")),
    ("support: share of D_U's safe-high transitions kept", ("support", "kept_by_group", "safe-high")),
    ("support: share of the kept transitions with a cost", ("support", "costly_among_kept")),
    ("weight mass on transitions with a cost", ("weight_share", "cost>0", "weight")),
    ("nu's share of the advantage's variance", ("variance_share", "bellman")),
    ("effective sample size (share of the weighted set)", ("effective_sample_size",)),
)


def _diagnostic(results: dict, path: tuple[str, ...]) -> float | None:
    """The number at ``path`` in the run's ``dice_diagnostics`` (``None`` where it records none, or no number)."""
    value = results.get("dice_diagnostics")
    for key in path:
        value = value.get(key) if isinstance(value, dict) else None
    number = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    return float(value) if number else None


def diagnostics_markdown(experiment: Experiment) -> str:
    """The DICE diagnostics of the experiment's weighted methods as markdown (``""`` when no run has any): per
    task and method one table, a row per diagnostic of :data:`DIAGNOSTICS` and a column per level, each cell the
    mean over seeds in percent with the seeds' range. They say why a method's numbers move with the level: how
    much of D_U the support cut keeps and how precisely, where the weights put their mass, and how much of
    the weights' exponent is nu's.

    Example:
        >>> weights = {"role": "unlabeled", "support": {"kept": 0.4}, "effective_sample_size": 0.02}
        >>> run = {"seed": 0, "dice_diagnostics": weights}
        >>> print(diagnostics_markdown(Experiment("fig", "n", {("pc1", 2, "spoildice"): [run]})))
        **pc1, SpoilDICE: DICE diagnostics, weights on unlabeled** (percent, mean over seeds [range])
        <BLANKLINE>
        | diagnostic | 2 |
        |---|---|
        | support: share of D_U kept | 40.0 [40.0, 40.0] |
        | effective sample size (share of the weighted set) | 2.0 [2.0, 2.0] |
    """
    levels, lines = experiment.levels, []
    for dataset in experiment.datasets:
        for algo in experiment.algos:
            groups = [experiment.cells.get((dataset, value, algo), []) for value in levels]
            rows = []
            for name, path in DIAGNOSTICS:
                cells = []
                for group in groups:
                    values = [v for v in (_diagnostic(r, path) for r in group) if v is not None]
                    cells.append(
                        f"{100 * sum(values) / len(values):.1f} [{100 * min(values):.1f}, {100 * max(values):.1f}]"
                        if values
                        else "-"
                    )
                if any(cell != "-" for cell in cells):
                    rows.append(f"| {name} | " + " | ".join(cells) + " |")
            if rows:
                roles = {
                    str(r["dice_diagnostics"].get("role"))
                    for g in groups
                    for r in g
                    if isinstance(r.get("dice_diagnostics"), dict)
                }
                title = f"**{dataset}, {ALGORITHM_NAMES.get(algo, algo)}: DICE diagnostics, weights on "
                title += f"{' / '.join(sorted(roles))}**"
                lines += [f"{title} (percent, mean over seeds [range])", ""]
                lines += _head("diagnostic", levels, experiment.level)
                lines += [*rows, ""]
    return "\n".join(lines).rstrip("\n")


def score_matrices(experiment: Experiment, metric: str, level=None, *, over_levels: bool = False) -> dict:
    """Per method, its scores as a (runs, tasks) array for :mod:`~spoil_torchrl.eval.aggregate`: the tasks are the
    datasets at ``level`` (or every (dataset, level) pair with ``over_levels``), the runs the seeds every one of
    them has (methods missing a task are left out)."""
    import numpy as np

    strata = [(d, v) for d in experiment.datasets for v in experiment.levels if over_levels or v == level]
    out = {}
    for algo in experiment.algos:
        groups = [experiment.cells.get((d, v, algo)) for d, v in strata]
        if not groups or any(g is None for g in groups):
            continue
        seeds = sorted(set.intersection(*({r["seed"] for r in g} for g in groups)))
        if not seeds:
            continue
        out[algo] = np.array(
            [[next(r for r in g if r["seed"] == s)["aggregate"][metric] for g in groups] for s in seeds],
            dtype=np.float64,
        )
    return out


def experiment_statistics(experiment: Experiment, *, reps: int = 2000, seed: int = 0) -> str:
    """Markdown: the interquartile mean of the normalised feasible return with its 95 % stratified-bootstrap
    interval over seeds and tasks, per level and method, and the probability that SpoilDICE's feasible return
    beats each baseline's, over every task and level (:mod:`spoil_torchrl.eval.aggregate`)."""
    from spoil_torchrl.eval.aggregate import interval_estimates, probability_of_improvement

    metric = "normalized_feasible_return"
    levels, algos = experiment.levels, experiment.algos
    estimates = {}  # a level where no method has every task yet (a sweep still running) shows "-"
    for value in levels:
        scores = score_matrices(experiment, metric, value)
        estimates[value] = (
            interval_estimates(scores, statistics=("iqm",), reps=reps, seed=seed) if scores else {}
        )
    lines = [
        "Interquartile mean of the normalised feasible return [95 % stratified-bootstrap interval] over seeds "
        "and tasks:",
        "",
        *_head("method", levels, experiment.level),
    ]
    for algo in algos:
        cells = []
        for value in levels:
            est = estimates[value].get(algo)
            cells.append("-" if est is None else "{:.2f} [{:.2f}, {:.2f}]".format(*est["iqm"]))
        lines.append(f"| {ALGORITHM_NAMES.get(algo, algo)} | " + " | ".join(cells) + " |")
    pooled = score_matrices(experiment, metric, over_levels=True)
    pairs = [("spoildice", a) for a in algos if a != "spoildice" and a in pooled and "spoildice" in pooled]
    if pairs:
        improvement = probability_of_improvement(pooled, pairs, reps=reps, seed=seed)
        lines += [
            "",
            "Probability that SpoilDICE's normalised feasible return exceeds the method's on a task and level "
            "(ties count half) [95 % interval]:",
            "",
            "| method | P(SpoilDICE > method) |",
            "|---|---|",
        ]
        for pair in pairs:
            lines.append(
                f"| {ALGORITHM_NAMES.get(pair[1], pair[1])} | "
                + "{:.2f} [{:.2f}, {:.2f}]".format(*improvement[pair])
                + " |"
            )
    return "\n".join(lines)
