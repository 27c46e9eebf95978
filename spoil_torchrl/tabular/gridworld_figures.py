"""The figures of the tabular gridworld experiment (section 5.1, appendix E): one seed's layout with the optimal
routes (Figure 3a), the return / cost trade-off (Figure 3b) and the quality curves (Figure A)."""

from __future__ import annotations

from pathlib import Path

import matplotlib
import numpy as np

from spoil_torchrl.tabular.gridworld import Demonstrators, Gridworld

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the Agg backend)

#: The strict problem of Eq. (4), the method the experiment checks for solvability.
STRICT = "SpoilDICE (Eq. 4)"
#: The two sweeps of the experiment and their panel titles.
SWEEPS = {
    "safeness": "d_P safeness xi varied (d_S performance o fixed)",
    "performance": "d_S performance o varied (d_P safeness xi fixed)",
}
STYLE = {
    "BC": ("tab:gray", "s"),
    "FBC": ("tab:orange", "^"),
    "DemoDICE": ("tab:blue", "D"),
    STRICT: ("tab:olive", "v"),
}


def _style(method: str) -> tuple[str, str]:
    return STYLE.get(method, ("tab:green", "o"))


def _likeliest_route(grid: Gridworld, d: np.ndarray) -> list[tuple[int, int]]:
    """The cells the policy of occupancy ``d`` visits from the start when every move goes where it was meant."""
    route, cell = [grid.start], grid.cell(*grid.start)
    goal = grid.cell(*grid.goal)
    while cell != goal and len(route) <= 4 * grid.size * grid.size:
        action = int(np.argmax(d[cell]))
        cell = int(np.argmax(grid.mdp.transition[cell, action]))
        route.append(divmod(cell, grid.size))
    return route


def plot_layout(grid: Gridworld, demo: Demonstrators, seed: int, path: Path) -> None:
    """Figure 3a: one seed's zones, start and goal, and the most likely routes of d*_M and d*_Mc."""
    size = grid.size
    fig, ax = plt.subplots(figsize=(5, 5))
    zone_colors = matplotlib.colors.ListedColormap(["white", "tab:olive"])
    ax.imshow(grid.zone[: size * size].reshape(size, size), cmap=zone_colors, vmin=0, vmax=1, alpha=0.8)
    for name, d, color, offset in (
        ("d*_M (unconstrained optimum)", demo.d_mdp, "tab:red", -0.12),
        ("d*_Mc (CMDP optimum)", demo.d_cmdp, "tab:blue", 0.12),
    ):
        rows, cols = np.array(_likeliest_route(grid, d)).T
        ax.plot(cols + offset, rows + offset, color=color, linewidth=2.2, marker=".", label=name)
    for (r, c), color, label in ((grid.start, "tab:orange", "start"), (grid.goal, "tab:green", "goal")):
        ax.scatter([c], [r], s=260, color=color, edgecolor="k", zorder=3, label=label)
    ax.set_xticks(np.arange(-0.5, size), minor=True)
    ax.set_yticks(np.arange(-0.5, size), minor=True)
    ax.grid(which="minor", color="0.75", linewidth=0.5)
    ax.tick_params(which="both", length=0)
    ax.set_title(f"seed {seed}: zones centred at {list(grid.zone_centers)} (olive)", fontsize=10)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.06), ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_tradeoff(summary: dict, methods: list[str], title: str, path: Path) -> None:
    """Figure 3b: normalised cost (x) against normalised return (y), one marker per method and level.

    ``summary``: sweep -> level -> method -> ``{"n", "return": (mean, se), "cost": (mean, se)}``."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), sharey=True)
    for ax, (sweep, title) in zip(axes, SWEEPS.items(), strict=True):
        ax.axvspan(0, 1, color="tab:green", alpha=0.08, label="feasible (cost <= delta_c)")
        for method in methods:
            color, marker = _style(method)
            pts = [(q, summary[sweep][q][method]) for q in summary[sweep] if summary[sweep][q][method]["n"]]
            xs = [e["cost"][0] for _, e in pts]
            ys = [e["return"][0] for _, e in pts]
            ax.plot(xs, ys, color=color, marker=marker, linestyle=":", label=method, alpha=0.85)
            for (q, _), x, y in zip(pts, xs, ys, strict=True):
                ax.annotate(
                    f"{100 * q:g}%",
                    (x, y),
                    textcoords="offset points",
                    xytext=(4, 4),
                    fontsize=7,
                    color=color,
                )
        ax.set_xscale("symlog", linthresh=1.0)
        ax.set_xlim(left=0)
        ax.set_xlabel("normalised cost  J(pi; c) / delta_c")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("normalised return (0 random, 1 CMDP optimum)")
    axes[1].legend(fontsize=8, loc="lower right")
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_quality_curves(summary: dict, methods: list[str], path: Path) -> None:
    """Figure A: normalised return (top) and cost (bottom) against the quality level, for both sweeps."""
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for col, (sweep, title) in enumerate(SWEEPS.items()):
        levels = sorted(summary[sweep])
        for row, key in enumerate(("return", "cost")):
            ax = axes[row, col]
            for method in methods:
                color, marker = _style(method)
                pts = [(q, summary[sweep][q][method]) for q in levels if summary[sweep][q][method]["n"]]
                qs = [100 * q for q, _ in pts]
                mean = np.array([e[key][0] for _, e in pts])
                se = np.nan_to_num(np.array([e[key][1] for _, e in pts]))  # nan for one seed: no bar
                ax.errorbar(qs, mean, yerr=se, color=color, marker=marker, capsize=3, label=method)
            if key == "cost":
                ax.axhline(1.0, color="k", linestyle="--", linewidth=0.8)
                ax.set_yscale("symlog", linthresh=1.0)
                ax.set_ylim(bottom=0)
                ax.set_xlabel("quality level (%)")
            ax.set_ylabel(f"normalised {key}")
            ax.grid(alpha=0.3)
        axes[0, col].set_title(title, fontsize=10)
    axes[0, 1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
