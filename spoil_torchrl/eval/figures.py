"""Figures of a comparison: the cost / feasible-return trade-off and the learning curves.

Both take per-(dataset, algorithm) summaries (as ``recipes/report.py`` makes them) and draw every algorithm
in one colour and marker on every panel (:func:`algorithm_style`), with one legend for the whole figure,
outside the panels, so that no legend covers a point.

* :func:`plot_tradeoff`: normalised cost (x, square-root scale so that the crowd of safe results near 0 spreads
  out while 0 stays on the axis) against normalised feasible return (y, fitted to the points), one marker per
  algorithm with standard-error bars, the safe region (cost <= 1) shaded and its edge drawn.
* :func:`plot_learning_curves`: normalised feasible return and normalised cost against the training step,
  mean over seeds with the standard error shaded, the cost limit drawn.
* :func:`plot_levels`: a paper experiment (Fig. 4, B, H, I): both metrics against the experiment's level, mean
  over seeds with the standard error shaded, the safe region shaded, the average over tasks and each task.

Example:
    >>> import tempfile, pathlib
    >>> summary = {("d", "bc"): {"normalized_cost": (2.0, 0.5), "normalized_feasible_return": (0.6, 0.1)},
    ...            ("d", "spoildice"): {"normalized_cost": (0.4, 0.1), "normalized_feasible_return": (0.8, 0.0)}}
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "tradeoff.png"
    >>> plot_tradeoff(summary, path, names={"bc": "BC", "spoildice": "SpoilDICE"})
    >>> path.stat().st_size > 0
    True
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

__all__ = [
    "ALGORITHM_NAMES",
    "algorithm_order",
    "algorithm_style",
    "plot_learning_curves",
    "plot_levels",
    "plot_tradeoff",
]

#: Fixed colours and markers, in the paper's column order; later algorithms take the following ones.
_COLOURS = ("#1f77b4", "#ff7f0e", "#8c564b", "#2ca02c", "#9467bd", "#e377c2", "#7f7f7f", "#bcbd22", "#d62728")
_MARKERS = ("o", "s", "v", "D", "^", "P", "X", "<", "*")
#: x ticks of the trade-off panels (square-root scale: evenly spread near 0, sparse far out)
COST_TICKS = (0, 0.1, 0.25, 0.5, 1, 2, 4, 8, 16, 32)
#: The paper's column order (Table 1) and display names; algorithms not listed follow, sorted.
ALGORITHM_NAMES = {
    "bc": "BC",
    "fbc": "FBC",
    "jfbc": "JFBC",
    "demodice_s": "DemoDICE-S",
    "demodice_u": "DemoDICE-U",
    "dwbc_s": "DWBC-S",
    "safedice": "SafeDICE",
    "coptidice": "COptiDICE",
    "spoildice": "SpoilDICE",
}
PAPER_ORDER = tuple(ALGORITHM_NAMES)


def algorithm_order(algo: str, order: Sequence[str] = PAPER_ORDER) -> tuple[int, str]:
    """Sort key: the paper's column order, then any other algorithm by name."""
    return (order.index(algo) if algo in order else len(order), algo)


def algorithm_style(algo: str, order: Sequence[str] = PAPER_ORDER) -> dict:
    """Colour and marker of an algorithm, the same on every panel and figure (SpoilDICE: red star)."""
    index = order.index(algo) if algo in order else len(order) + sum(map(ord, algo))
    return {"color": _COLOURS[index % len(_COLOURS)], "marker": _MARKERS[index % len(_MARKERS)]}


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _grid(plt, panels: int, rows_per_panel: int = 1, width: float = 4.6, height: float = 3.6):
    cols = min(panels, 3)
    rows = math.ceil(panels / cols)
    fig, axes = plt.subplots(
        rows * rows_per_panel, cols, figsize=(width * cols, height * rows * rows_per_panel), squeeze=False
    )
    return fig, axes, cols


def _datasets_and_algos(keys, order: Sequence[str]) -> tuple[list[str], list[str]]:
    datasets = sorted({d for d, _ in keys})
    algos = sorted({a for _, a in keys}, key=lambda a: algorithm_order(a, order))
    return datasets, algos


def _shared_legend(fig, algos, names: Mapping[str, str], order, extra: Sequence = ()) -> float:
    """One legend below the panels, in as many columns as the figure's width holds (at most 6); returns the
    share of the figure's height it takes, for ``tight_layout(rect=...)``."""
    from matplotlib.lines import Line2D

    handles = [
        Line2D([], [], linestyle="none", markersize=8, **algorithm_style(a, order), label=names.get(a, a))
        for a in algos
    ]
    entries = len(handles) + len(extra)
    ncol = max(1, min(entries, 6, int(fig.get_figwidth() // 1.35)))
    fig.legend(
        handles=[*handles, *extra],
        loc="lower center",
        ncol=ncol,
        frameon=False,
        bbox_to_anchor=(0.5, 0.0),
    )
    rows = -(-entries // ncol)
    return (0.1 + 0.28 * rows) / fig.get_figheight()  # a row of legend is about 0.28 inch


def _nan0(value: float) -> float:
    return 0.0 if math.isnan(value) else value


def plot_tradeoff(
    summary: Mapping[tuple[str, str], Mapping],
    path: str | Path,
    *,
    names: Mapping[str, str] | None = None,
    order: Sequence[str] = PAPER_ORDER,
) -> None:
    """Save the trade-off scatter: one panel per dataset, x = normalised cost, y = normalised feasible return.

    ``summary[(dataset, algo)]`` holds ``normalized_cost`` and ``normalized_feasible_return`` as
    ``(mean, standard error)`` (NaN error for a single seed: no bar).
    """
    from matplotlib.patches import Patch

    plt, names = _pyplot(), dict(ALGORITHM_NAMES if names is None else names)
    datasets, algos = _datasets_and_algos(summary, order)
    fig, axes, cols = _grid(plt, len(datasets))
    for i, dataset in enumerate(datasets):
        ax = axes[i // cols][i % cols]
        rows = {a: summary[(dataset, a)] for a in algos if (dataset, a) in summary}
        x_hi = [m + _nan0(e) for m, e in (r["normalized_cost"] for r in rows.values())]
        y_lo = [m - _nan0(e) for m, e in (r["normalized_feasible_return"] for r in rows.values())]
        y_hi = [m + _nan0(e) for m, e in (r["normalized_feasible_return"] for r in rows.values())]
        x_max = max(1.5, *x_hi) * 1.08
        ax.set_xscale("function", functions=(_sqrt, _square))
        ax.axvspan(0, 1, color="tab:green", alpha=0.12, zorder=0)
        ax.axvline(1.0, color="tab:green", linewidth=1, zorder=1)
        for algo, row in rows.items():
            (x, xe), (y, ye) = row["normalized_cost"], row["normalized_feasible_return"]
            style = algorithm_style(algo, order)
            ax.errorbar(
                x,
                y,
                xerr=_nan0(xe),
                yerr=_nan0(ye),
                fmt=style["marker"],
                color=style["color"],
                markersize=8 if algo == "spoildice" else 6,
                capsize=3,
                alpha=0.9,
                zorder=3,
            )
        span = max(y_hi) - min(y_lo)
        ax.set_ylim(min(y_lo) - 0.08 * span - 0.01, max(y_hi) + 0.08 * span + 0.01)
        ax.set_xlim(0, x_max)
        ticks = _spread_ticks(x_max)
        ax.set_xticks(ticks)
        ax.set_xticklabels([f"{t:g}" for t in ticks])
        ax.set_xlabel("normalised cost (square-root scale)")
        ax.set_ylabel("normalised feasible return")
        ax.set_title(dataset, fontsize=10)
        ax.grid(alpha=0.3)
    for j in range(len(datasets), len(axes) * cols):
        axes[j // cols][j % cols].axis("off")
    safe = Patch(color="tab:green", alpha=0.25, label="safe (cost <= 1)")
    below = _shared_legend(fig, algos, names, order, extra=[safe])
    fig.tight_layout(rect=(0, below, 1, 1))
    _save(plt, fig, path)


def _spread_ticks(x_max: float, gap: float = 0.1) -> list[float]:
    """The :data:`COST_TICKS` up to ``x_max`` that lie at least ``gap`` of the axis apart on the square-root
    scale (labels never overlap).

    >>> _spread_ticks(1.6), _spread_ticks(8.0)
    ([0, 0.1, 0.25, 0.5, 1], [0, 0.1, 0.5, 1, 2, 4, 8])
    """
    kept: list[float] = []
    for tick in (t for t in COST_TICKS if t <= x_max):
        if not kept or (math.sqrt(tick) - math.sqrt(kept[-1])) / math.sqrt(x_max) >= gap:
            kept.append(tick)
    return kept


def _sqrt(x):
    import numpy as np

    return np.sqrt(np.clip(x, 0, None))


def _square(x):
    return x**2


def plot_learning_curves(
    curves: Mapping[tuple[str, str], Mapping],
    path: str | Path,
    *,
    seeds: Callable[[str, str], int] | None = None,
    names: Mapping[str, str] | None = None,
    order: Sequence[str] = PAPER_ORDER,
) -> None:
    """Save the learning curves: per dataset, normalised feasible return (upper panel) and normalised cost
    (lower panel) against the training step, mean over seeds with the standard error shaded.

    ``curves[(dataset, algo)]`` holds ``steps`` and, for both metrics, one ``(mean, standard error)`` per step;
    ``seeds(dataset, algo)`` (optional) gives the seed count written in the panel's title line.
    """
    from matplotlib.lines import Line2D

    plt, names = _pyplot(), dict(ALGORITHM_NAMES if names is None else names)
    datasets, algos = _datasets_and_algos(curves, order)
    fig, axes, cols = _grid(plt, len(datasets), rows_per_panel=2, height=3.0)
    metrics = (
        ("normalized_feasible_return", "normalised feasible return"),
        ("normalized_cost", "normalised cost"),
    )
    for i, dataset in enumerate(datasets):
        top, col = 2 * (i // cols), i % cols
        counts = []
        for algo in algos:
            if (dataset, algo) not in curves:
                continue
            c = curves[(dataset, algo)]
            if seeds is not None:
                counts.append(seeds(dataset, algo))
            color = algorithm_style(algo, order)["color"]
            for row, (metric, _) in enumerate(metrics):
                mean = [m for m, _ in c[metric]]
                se = [_nan0(e) for _, e in c[metric]]
                ax = axes[top + row][col]
                ax.plot(c["steps"], mean, color=color, linewidth=2 if algo == "spoildice" else 1.2)
                ax.fill_between(
                    c["steps"],
                    [m - e for m, e in zip(mean, se, strict=True)],
                    [m + e for m, e in zip(mean, se, strict=True)],
                    color=color,
                    alpha=0.15,
                    linewidth=0,
                )
        low, high = (min(counts), max(counts)) if counts else (None, None)
        seeds_text = "" if low is None else f" ({low} seeds)" if low == high else f" ({low}-{high} seeds)"
        axes[top][col].set_title(dataset + seeds_text, fontsize=10)
        for row, (_, label) in enumerate(metrics):
            axes[top + row][col].set_ylabel(label)
            axes[top + row][col].grid(alpha=0.3)
        axes[top + 1][col].axhline(1.0, color="tab:green", linestyle="--", linewidth=1)
        axes[top + 1][col].set_xlabel("training step")
    for j in range(len(datasets), (len(axes) // 2) * cols):
        axes[2 * (j // cols)][j % cols].axis("off")
        axes[2 * (j // cols) + 1][j % cols].axis("off")
    limit = Line2D([], [], color="tab:green", linestyle="--", label="cost limit")
    handles = [Line2D([], [], color=algorithm_style(a, order)["color"], label=names.get(a, a)) for a in algos]
    fig.legend(handles=[*handles, limit], loc="lower center", ncol=min(len(handles) + 1, 6), frameon=False)
    fig.tight_layout(rect=(0, 0.06 if len(axes) > 2 else 0.1, 1, 1))
    _save(plt, fig, path)


def plot_levels(
    panels: Sequence[tuple[str, Mapping[tuple, Mapping]]],
    levels: Sequence,
    path: str | Path,
    *,
    level_name: str,
    names: Mapping[str, str] | None = None,
    order: Sequence[str] = PAPER_ORDER,
) -> None:
    """Save an experiment's figure: one column per panel (e.g. the average over tasks, then each task),
    normalised feasible return (upper row) and normalised cost (lower row, square-root scale, safe region
    shaded) against the level, one line per method with the standard error shaded.

    ``panels`` is a list of ``(title, rows)`` with ``rows[(level, algo)]`` holding both metrics as
    ``(mean, standard error)``; ``levels`` are drawn evenly spaced, in the given order, and labelled.

    Examples:
        >>> import tempfile, pathlib
        >>> rows = {(v, a): {"normalized_feasible_return": (0.5 + v / 4, 0.05), "normalized_cost": (c * v, 0.1)}
        ...         for v in (0.25, 0.75) for a, c in (("bc", 4.0), ("spoildice", 0.5))}
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "fig.png"
        >>> plot_levels([("average", rows)], [0.25, 0.75], path, level_name="performance")
        >>> path.stat().st_size > 0
        True
    """
    from matplotlib.patches import Patch

    plt, names = _pyplot(), dict(ALGORITHM_NAMES if names is None else names)
    algos = sorted({a for _, rows in panels for _, a in rows}, key=lambda a: algorithm_order(a, order))
    fig, axes = plt.subplots(2, len(panels), figsize=(4.2 * len(panels), 6.4), squeeze=False)
    x = list(range(len(levels)))
    for col, (title, rows) in enumerate(panels):
        top, bottom = axes[0][col], axes[1][col]
        cost_max = 1.5
        for algo in algos:
            points = [(i, rows[(v, algo)]) for i, v in enumerate(levels) if (v, algo) in rows]
            if not points:
                continue
            style = algorithm_style(algo, order)
            for ax, metric in ((top, "normalized_feasible_return"), (bottom, "normalized_cost")):
                xs = [i for i, _ in points]
                mean = [r[metric][0] for _, r in points]
                se = [_nan0(r[metric][1]) for _, r in points]
                lo = [
                    max(m - e, 0.0) if metric == "normalized_cost" else m - e
                    for m, e in zip(mean, se, strict=True)
                ]
                hi = [m + e for m, e in zip(mean, se, strict=True)]
                if metric == "normalized_cost":
                    cost_max = max(cost_max, *hi)
                ax.plot(
                    xs,
                    mean,
                    color=style["color"],
                    marker=style["marker"],
                    markersize=5,
                    linewidth=2 if algo == "spoildice" else 1.2,
                )
                ax.fill_between(xs, lo, hi, color=style["color"], alpha=0.15, linewidth=0)
        top.set_title(title, fontsize=10)
        top.set_ylabel("normalised feasible return")
        bottom.set_yscale("function", functions=(_sqrt, _square))
        bottom.set_ylim(0, cost_max * 1.08)
        ticks = _spread_ticks(cost_max * 1.08)
        bottom.set_yticks(ticks)
        bottom.set_yticklabels([f"{t:g}" for t in ticks])
        bottom.axhspan(0, 1, color="tab:green", alpha=0.12, zorder=0)
        bottom.axhline(1.0, color="tab:green", linewidth=1)
        bottom.set_ylabel("normalised cost (square-root scale)")
        for ax in (top, bottom):
            ax.set_xticks(x)
            ax.set_xticklabels([f"{v:g}" if isinstance(v, float) else str(v) for v in levels])
            ax.set_xlim(-0.3, len(levels) - 0.7)
            ax.grid(alpha=0.3)
        bottom.set_xlabel(level_name)
    safe = Patch(color="tab:green", alpha=0.25, label="safe (cost <= 1)")
    below = _shared_legend(fig, algos, names, order, extra=[safe])
    fig.tight_layout(rect=(0, below, 1, 1))
    _save(plt, fig, path)


def _save(plt, fig, path: str | Path) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
