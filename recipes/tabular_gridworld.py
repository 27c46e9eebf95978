"""The tabular gridworld experiment (section 5.1, appendix E): Figure 3b and Figure A with exact solvers.

For each seed (one random zone layout): solve d*_M and d*_Mc by linear programming, build d_P (safeness xi)
and d_S (performance o) at each quality level, solve every Table B objective exactly for each hyper-parameter,
evaluate the extracted policies exactly, and keep per method the highest-return feasible policy, else the
lowest-cost one (appendix E.2). Writes ``results.json``, ``results.md`` and three PNGs (the first seed's layout
with the optimal routes, Figure 3b's trade-off, Figure A's quality curves) into the Hydra run dir.

    python recipes/tabular_gridworld.py seeds=5 grid.layout=along grid.cost_model=transition

The settings are checked before anything is solved
(:func:`~spoil_torchrl.tabular.settings.check_gridworld_settings`): a value a setting
cannot take ends the command in one ``error:`` line naming it, with exit status 2.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import hydra
import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from tqdm.auto import tqdm

from spoil_torchrl.eval.tables import mean_stderr
from spoil_torchrl.runs.outcome import ended_in_one_line
from spoil_torchrl.runs.settings import check_settings
from spoil_torchrl.tabular import (
    InfeasibleProblemError,
    evaluate,
    solve_bc,
    solve_demodice,
    solve_fbc,
    solve_spoildice,
    solve_spoildice_lagrangian,
)
from spoil_torchrl.tabular.gridworld import (
    Gridworld,
    make_demonstrators,
    make_gridworld,
    performant_distribution,
    route_lengths,
    safe_distribution,
)
from spoil_torchrl.tabular.gridworld_figures import (
    STRICT,
    SWEEPS,
    plot_layout,
    plot_quality_curves,
    plot_tradeoff,
)
from spoil_torchrl.tabular.protocol import is_feasible, normalise, select_candidate
from spoil_torchrl.tabular.settings import check_gridworld_settings

log = logging.getLogger(__name__)


def seed_list(seeds) -> list[int]:
    """``seeds`` is an int n (seeds 0 .. n-1) or a list of seeds."""
    if isinstance(seeds, int):
        return list(range(seeds))
    return [int(s) for s in seeds]


def problems(cfg: DictConfig) -> list[tuple[str, float, float, float]]:
    """(sweep, level, xi, o) for both panels of Figure 3b."""
    fixed = float(cfg.fixed_level)
    out = [("safeness", float(q), float(q), fixed) for q in cfg.levels]
    return out + [("performance", float(q), fixed, float(q)) for q in cfg.levels]


def method_names(cfg: DictConfig) -> list[str]:
    names = ["BC", "FBC", "DemoDICE", STRICT]
    lam = lagrange(cfg)
    return names + ([f"SpoilDICE (Eq. 6, lambda={lam:g})"] if lam is not None else [])


def lagrange(cfg: DictConfig) -> float | None:
    value = cfg.methods.spoildice_lagrange
    return None if value is None else float(value)


def solve_all(cfg: DictConfig, mdp, d_P: np.ndarray, d_S: np.ndarray) -> dict[str, list[dict]]:
    """Every method at every hyper-parameter: one candidate dict per solve (``solved=False`` if infeasible)."""
    thresholds = [float(t) for t in cfg.methods.thresholds]
    solvers = {
        "BC": [("none", None, lambda _: solve_bc(d_P))],
        "FBC": [("threshold", t, lambda t: solve_fbc(d_P, d_S, t)) for t in thresholds],
        "DemoDICE": [
            ("alpha", float(a), lambda a: solve_demodice(mdp, d_P, d_S, a))
            for a in cfg.methods.demodice_alphas
        ],
        STRICT: [("threshold", t, lambda t: solve_spoildice(mdp, d_P, d_S, t)) for t in thresholds],
    }
    lam = lagrange(cfg)
    if lam is not None:
        solvers[method_names(cfg)[-1]] = [
            ("threshold", t, lambda t: solve_spoildice_lagrangian(mdp, d_P, d_S, t, lagrange=lam))
            for t in thresholds
        ]
    out: dict[str, list[dict]] = {}
    for method, grid in solvers.items():
        out[method] = []
        cache: dict[bytes, tuple[float, float]] = {}  # same support -> same solution
        for name, value, solve in grid:
            key = (d_S > value).tobytes() if name == "threshold" else None
            try:
                if key is not None and key in cache:
                    ret, cost = cache[key]
                else:
                    ret, cost = evaluate(mdp, solve(value))
                    if key is not None:
                        cache[key] = (ret, cost)
            except InfeasibleProblemError:
                out[method].append({name: value, "solved": False})
                continue
            out[method].append({name: value, "solved": True, "return": ret, "cost": cost})
    return out


def mean_se(values) -> tuple[float, float]:
    """Mean and standard error over seeds (:func:`~spoil_torchrl.eval.tables.mean_stderr`: nan for one seed)."""
    return mean_stderr(torch.tensor([float(v) for v in values], dtype=torch.float64))


def make_grid(cfg: DictConfig, seed: int) -> Gridworld:
    return make_gridworld(seed, **OmegaConf.to_container(cfg.grid))


def run_seed(cfg: DictConfig, seed: int) -> dict:
    grid = make_grid(cfg, seed)
    mdp, limit = grid.mdp, grid.cost_limit
    demo = make_demonstrators(grid)
    scale = {"random_return": demo.random_return, "optimal_return": demo.optimal_return, "cost_limit": limit}

    def j(d):
        return float((d * mdp.reward).sum()), float((d * mdp.cost).sum())

    shortest, safe = route_lengths(grid)
    result = {
        "seed": seed,
        "start": list(grid.start),
        "goal": list(grid.goal),
        "zone_centers": list(grid.zone_centers),
        "route_lengths": {"shortest": shortest, "shortest_cost_free": safe},
        "references": {
            name: {"return": r, "cost": c, **normalise(r, c, **scale)}
            for name, (r, c) in {
                "d*_M (unconstrained optimum)": j(demo.d_mdp),
                "d*_Mc (CMDP optimum)": j(demo.d_cmdp),
                "d_0 (safe random-like, o = 0)": j(demo.d_random),
            }.items()
        },
        "problems": [],
    }
    solved: dict[tuple[float, float], dict] = {}
    for sweep, level, xi, o in problems(cfg):
        if (xi, o) not in solved:
            d_P = performant_distribution(demo.d_mdp, demo.d_cmdp, xi)
            d_S = safe_distribution(demo.d_cmdp, demo.d_random, o)
            candidates = solve_all(cfg, mdp, d_P, d_S)
            selected = {}
            for method, cands in candidates.items():
                usable = [c for c in cands if c["solved"]]
                if not usable:  # e.g. SpoilDICE when every threshold violates Eq. (14)
                    selected[method] = None
                    continue
                chosen = select_candidate(usable, limit)
                selected[method] = {**chosen, **normalise(chosen["return"], chosen["cost"], **scale)}
            solved[(xi, o)] = {"selected": selected, "candidates": candidates}
        result["problems"].append({"sweep": sweep, "level": level, "xi": xi, "o": o, **solved[(xi, o)]})
    return result


def summarise(cfg: DictConfig, results: list[dict]) -> dict:
    """summary[sweep][level][method] = mean and standard error over seeds of the selected policies."""
    summary: dict = {}
    for sweep, level, _, _ in problems(cfg):
        row = {}
        for method in method_names(cfg):
            picked = [
                p["selected"][method]
                for r in results
                for p in r["problems"]
                if p["sweep"] == sweep and p["level"] == level and p["selected"][method] is not None
            ]
            if not picked:
                row[method] = {"n": 0}
                continue
            row[method] = {
                "n": len(picked),
                "return": mean_se([p["normalised_return"] for p in picked]),
                "cost": mean_se([p["normalised_cost"] for p in picked]),
                "feasible": float(np.mean([p["feasible"] for p in picked])),
            }
        summary.setdefault(sweep, {})[level] = row
    return summary


def solvability(results: list[dict], method: str) -> dict[str, float]:
    """Share of problems (seeds x quality pairs) for which ``method`` had a solution at each hyper-parameter."""
    counts: dict[str, list[bool]] = {}
    for r in results:
        seen = set()
        for p in r["problems"]:
            if (p["xi"], p["o"]) in seen:
                continue
            seen.add((p["xi"], p["o"]))
            for c in p["candidates"][method]:
                counts.setdefault(f"{c['threshold']:g}", []).append(c["solved"])
    return {t: float(np.mean(v)) for t, v in counts.items()}


def reference_summary(results: list[dict], limit: float) -> dict:
    names = list(results[0]["references"])
    out = {}
    for name in names:
        rows = [r["references"][name] for r in results]
        out[name] = {
            "return": mean_se([x["normalised_return"] for x in rows]),
            "cost": mean_se([x["normalised_cost"] for x in rows]),
            "feasible": float(np.mean([is_feasible(x["cost"], limit) for x in rows])),
            "max_cost": float(max(x["normalised_cost"] for x in rows)),
        }
    return out


def pm(mean_and_se: tuple[float, float], digits: int) -> str:
    """``"mean ± se"``; the mean alone where the standard error is undefined (a single seed: nan).

    Examples:
        >>> pm((1.0, 0.25), 2), pm((1.0, float("nan")), 2)
        ('1.00 ± 0.25', '1.00')
    """
    mean, se = mean_and_se
    return f"{mean:.{digits}f} ± {se:.{digits}f}" if np.isfinite(se) else f"{mean:.{digits}f}"


def _cell(entry: dict) -> str:
    if entry["n"] == 0:
        return "no solution"
    return f"{pm(entry['return'], 3)} / {pm(entry['cost'], 2)} ({100 * entry['feasible']:.0f}%)"


def route_summary(results: list[dict]) -> str:
    """One line on how much longer the cost-free routes are than the shortest ones, over the seeds."""
    extra = [
        r["route_lengths"]["shortest_cost_free"] - r["route_lengths"]["shortest"]
        for r in results
        if r["route_lengths"]["shortest_cost_free"] is not None
    ]
    shortest = sorted({r["route_lengths"]["shortest"] for r in results})
    text = (
        f"Shortest route: {'/'.join(map(str, shortest))} moves; the shortest cost-free route is longer by "
        f"{min(extra)} .. {max(extra)} moves (mean {np.mean(extra):.1f}); it is as short in "
        f"{sum(e == 0 for e in extra)} of {len(results)} seeds"
    )
    missing = len(results) - len(extra)
    return text + (f"; {missing} seeds have no cost-free route." if missing else ".")


def to_json(value):
    """``value`` with nan (the standard error of a single seed) mapped to ``None`` (JSON ``null``)."""
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: to_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_json(v) for v in value]
    return value


def markdown(cfg: DictConfig, summary: dict, references: dict, solvable: dict, results: list[dict]) -> str:
    levels = [float(q) for q in cfg.levels]
    n_seeds = len(results)
    se = "mean ± standard error" if n_seeds > 1 else "the value (no standard error for one seed)"
    lines = [
        f"Normalised return (0 = uniform random, 1 = CMDP optimum) / normalised cost (J(pi; c) / delta_c), "
        f"{se} over {n_seeds} seeds, and the share of seeds whose selected policy is feasible "
        f"(cost <= delta_c). Layout: `{cfg.grid.layout}`; cost model: `{cfg.grid.cost_model}`; the fixed "
        f"quality is {cfg.fixed_level:g}. {route_summary(results)}",
        "",
    ]
    for sweep, title in SWEEPS.items():
        lines += [f"**{title}**", ""]
        lines.append("| method | " + " | ".join(f"{100 * q:g}%" for q in levels) + " |")
        lines.append("|---" * (len(levels) + 1) + "|")
        for method in method_names(cfg):
            cells = [_cell(summary[sweep][q][method]) for q in levels]
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += [
        "**Reference occupancies**",
        "",
        "| occupancy | return | cost | feasible | max cost |",
        "|---|---|---|---|---|",
    ]
    for name, ref in references.items():
        lines.append(
            f"| {name} | {pm(ref['return'], 3)} | {pm(ref['cost'], 3)} | {100 * ref['feasible']:.0f}% "
            f"| {ref['max_cost']:.3f} |"
        )
    lines += [
        "",
        f"Share of problems where {STRICT} has a solution (the support admits an occupancy, Eq. 14), per "
        "threshold: " + ", ".join(f"{t}: {100 * v:.0f}%" for t, v in solvable.items()),
    ]
    return "\n".join(lines)


@hydra.main(config_path="../configs", config_name="tabular_gridworld", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    with ended_in_one_line("recipes/tabular_gridworld.py", run_dir):  # a bad setting: one line, exit status 2
        settings = OmegaConf.to_container(cfg, resolve=True)
        check_settings({"progress": settings["progress"]})
        check_gridworld_settings(settings)
    seeds = seed_list(cfg.seeds)
    start = time.perf_counter()
    results = [run_seed(cfg, seed) for seed in tqdm(seeds, desc="seeds", disable=not cfg.progress)]
    summary = summarise(cfg, results)
    references = reference_summary(results, float(cfg.grid.cost_limit))
    solvable = solvability(results, STRICT)
    table = markdown(cfg, summary, references, solvable, results)
    seconds = time.perf_counter() - start
    (run_dir / "results.md").write_text(table + "\n")
    payload = {
        "config": OmegaConf.to_container(cfg),
        "seconds": seconds,
        "summary": {sweep: {str(q): row for q, row in levels.items()} for sweep, levels in summary.items()},
        "references": references,
        "strict_spoildice_solvable": solvable,
        "seeds": results,
    }
    (run_dir / "results.json").write_text(json.dumps(to_json(payload), indent=1, allow_nan=False))
    if cfg.figures:
        grid = make_grid(cfg, seeds[0])
        plot_layout(grid, make_demonstrators(grid), seeds[0], run_dir / "layout.png")
        title = f"Constrained gridworld, exact solutions (layout: {cfg.grid.layout}, cost model: {cfg.grid.cost_model})"
        plot_tradeoff(summary, method_names(cfg), title, run_dir / "tradeoff.png")
        plot_quality_curves(summary, method_names(cfg), run_dir / "quality.png")
    log.info(table)
    log.info(f"solved and evaluated {len(seeds)} seeds in {seconds:.1f} s; run directory: {run_dir}")
    return {"summary": summary}


if __name__ == "__main__":
    main()
