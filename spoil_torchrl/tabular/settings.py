"""The tabular recipes' settings, checked before anything is built, so that a typo never ends in a traceback
from deep inside a solver, nor after thousands of discriminator steps.

``recipes/tabular_spoildice.py`` checks its settings with :func:`check_tabular_settings`,
``recipes/tabular_gridworld.py`` with :func:`check_gridworld_settings`; the keys they share with the main recipe
(``threads``, ``progress``, the logger) are checked as the main recipe's are. Every rule is one of
:mod:`spoil_torchrl.rules`, and every problem a :class:`~spoil_torchrl.errors.SettingsError` naming the dotted
key, the value and what is expected, which ends the command in one ``error:`` line with exit status 2.
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Mapping
from typing import Any

from spoil_torchrl.errors import SettingsError
from spoil_torchrl.rules import (
    Rule,
    check_keys,
    check_section,
    layers,
    list_of,
    non_negative,
    number,
    open_unit,
    positive,
    positive_int,
    seed,
    switch,
    unit,
)
from spoil_torchrl.tabular.gridworld import COST_MODELS, LAYOUTS, make_gridworld, zone_candidates
from spoil_torchrl.tabular.neural import TabularTrainingConfig

#: The keys of ``training`` (:class:`~spoil_torchrl.tabular.neural.TabularTrainingConfig`; the recipe sets
#: ``seed`` per run).
TRAINING_SETTINGS = tuple(f.name for f in dataclasses.fields(TabularTrainingConfig) if f.name != "seed")
#: The keys of ``grid`` (:func:`~spoil_torchrl.tabular.gridworld.make_gridworld`'s keyword arguments).
GRID_SETTINGS = tuple(name for name in inspect.signature(make_gridworld).parameters if name != "seed")


_STEPS: Rule = (positive_int, "an integer >= 1")
_LR: Rule = (positive, "a finite number > 0")
_PENALTY: Rule = (non_negative, "a finite number >= 0")

#: ``problem`` of the tabular SpoilDICE check (:func:`~spoil_torchrl.tabular.problems.random_dual_demo_problem`):
#: every key is needed.
PROBLEM_RULES: dict[str, Rule] = {
    "n_states": _STEPS,
    "n_actions": (lambda v: positive_int(v) and v >= 2, "an integer >= 2"),
    "gamma": (open_unit, "a number in (0, 1)"),
    "slip": (unit, "a probability in [0, 1]"),
    "temperature": (positive, "a finite number > 0"),
}
#: ``training`` (:class:`~spoil_torchrl.tabular.neural.TabularTrainingConfig`: a key left out keeps its
#: default).
TRAINING_RULES: dict[str, Rule] = {
    "n_samples": _STEPS,
    "n_init": _STEPS,
    "batch_size": _STEPS,
    "discriminator_steps": _STEPS,
    "dice_steps": _STEPS,
    "discriminator_lr": _LR,
    "nu_lr": _LR,
    "lagrange_lr": _LR,
    "actor_lr": _LR,
    "discriminator_cells": (layers, "a list of layer sizes >= 1"),
    "discriminator_gradient_penalty": _PENALTY,
    "nu_gradient_penalty": _PENALTY,
    "kappa": (open_unit, "a quantile in (0, 1)"),
    "init_lagrange": (number, "a finite number"),
}


def _grid_cell(value: Any) -> bool:
    return isinstance(value, (list, tuple)) and len(value) == 2 and all(map(seed, value))


#: The gridworld recipe's top-level settings: every key is needed.
GRIDWORLD_RULES: dict[str, Rule] = {
    "seeds": (
        lambda v: positive_int(v) or list_of(seed, distinct=True)(v),
        "an integer n >= 1 (seeds 0 .. n-1) or a non-empty list of distinct integers >= 0",
    ),
    "levels": (list_of(unit, distinct=True), "a non-empty list of distinct shares in [0, 1]"),
    "fixed_level": (unit, "a share in [0, 1]"),
    "figures": (switch, "true or false"),
}
#: ``grid`` (:func:`~spoil_torchrl.tabular.gridworld.make_gridworld`: a key left out keeps its default).
GRID_RULES: dict[str, Rule] = {
    "size": (lambda v: positive_int(v) and v >= 2, "an integer >= 2"),
    "layout": (lambda v: v in LAYOUTS, " | ".join(LAYOUTS)),
    "n_zones": (lambda v: v is None or seed(v), "null (the layout's) or an integer >= 0"),
    "start": (lambda v: v is None or _grid_cell(v), "null (the layout's) or a cell [row, col]"),
    "goal": (lambda v: v is None or _grid_cell(v), "null (the layout's) or a cell [row, col]"),
    "slip": (lambda v: number(v) and 0 <= v < 0.75, "a probability in [0, 0.75)"),
    "gamma": (open_unit, "a number in (0, 1)"),
    "cost_limit": _PENALTY,
    "cost_model": (lambda v: v in COST_MODELS, " | ".join(COST_MODELS)),
}
#: ``methods``: the hyper-parameters each method is solved at; every key is needed.
METHOD_RULES: dict[str, Rule] = {
    "thresholds": (list_of(non_negative), "a non-empty list of finite numbers >= 0"),
    "demodice_alphas": (list_of(non_negative), "a non-empty list of finite numbers >= 0"),
    "spoildice_lagrange": (
        lambda v: v is None or non_negative(v),
        "null (no SpoilDICE-lambda row) or a finite number >= 0",
    ),
}


def check_tabular_settings(cfg: Mapping[str, Any]) -> None:
    """Raise :class:`~spoil_torchrl.errors.SettingsError` for the first setting of the tabular SpoilDICE
    check's resolved configuration ``cfg`` that cannot be right: ``seeds``, ``threads``, :data:`PROBLEM_RULES`
    (no other ``problem`` key), :data:`TRAINING_RULES` (no other ``training`` key) and the logger's experiment
    name. (``progress`` and ``logger.backend`` are the main recipe's settings, checked as there.)

    Examples:
        >>> check_tabular_settings({"seeds": []})
        Traceback (most recent call last):
        ...
        spoil_torchrl.errors.SettingsError: seeds = []: expected a non-empty list of distinct integers >= 0
    """
    check_keys(
        cfg,
        {
            "seeds": (list_of(seed, distinct=True), "a non-empty list of distinct integers >= 0"),
            "threads": _STEPS,  # torch's intra-op threads: more than the cores is slower, not wrong
        },
    )
    check_section(cfg, "problem", PROBLEM_RULES)
    check_section(cfg, "training", TRAINING_RULES, accepted=TRAINING_SETTINGS, every_key=False)
    name = cfg.get("logger", {}).get("experiment_name") if isinstance(cfg.get("logger"), Mapping) else None
    if not (isinstance(name, str) and name):
        raise SettingsError(
            f"logger.experiment_name = {name!r}: expected a non-empty name (quote one that reads as a "
            "number: logger.experiment_name='\"2024\"')"
        )


def check_gridworld_settings(cfg: Mapping[str, Any]) -> None:
    """Raise :class:`~spoil_torchrl.errors.SettingsError` for the first setting of the gridworld recipe's
    resolved configuration ``cfg`` that cannot be right: :data:`GRIDWORLD_RULES`, :data:`GRID_RULES` (and no
    other ``grid`` key; a start, goal and zones that fit the grid) and :data:`METHOD_RULES`. (``progress`` is
    the main recipe's setting, checked as there.)

    Examples:
        >>> check_gridworld_settings({"seeds": [0], "levels": [1.5]})  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        spoil_torchrl.errors.SettingsError: levels = [1.5]: expected a non-empty list of distinct shares ...
    """
    check_keys(cfg, GRIDWORLD_RULES)
    check_section(cfg, "grid", GRID_RULES, accepted=GRID_SETTINGS, every_key=False)
    check_grid_layout(cfg["grid"])
    check_section(cfg, "methods", METHOD_RULES)


def check_grid_layout(grid: Mapping) -> None:
    """Raise :class:`SettingsError` when the start, the goal or the number of zones of ``grid`` (given, or the
    layout's) does not fit a grid of ``grid.size``, as :func:`~spoil_torchrl.tabular.gridworld.make_gridworld`
    would refuse it. The values themselves are checked before (a size >= 2, a known layout, cells as
    ``[row, col]``, ``n_zones`` an integer >= 0 or null).

    Examples:
        >>> check_grid_layout({"size": 11, "layout": "across", "n_zones": 9})  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        spoil_torchrl.errors.SettingsError: grid.n_zones = 9: expected an integer from 0 to 7 ...
    """
    defaults = inspect.signature(make_gridworld).parameters
    size = grid.get("size", defaults["size"].default)
    layout = grid.get("layout", defaults["layout"].default)
    start_default, goal_default, zones_default = LAYOUTS[layout](size)
    cells = {}
    for key, default in (("start", start_default), ("goal", goal_default)):
        cell = grid.get(key)
        if cell is None:
            cell = default
        elif not all(0 <= v < size for v in cell):
            raise SettingsError(
                f"grid.{key} = {list(cell)!r}: expected a cell [row, col] inside the {size} x {size} grid"
            )
        cells[key] = tuple(cell)
    if cells["start"] == cells["goal"]:
        raise SettingsError(
            f"grid.start = grid.goal = {list(cells['start'])!r} (grid.size = {size}, layout {layout}): "
            "expected two different cells"
        )
    fit = len(zone_candidates(size, cells["start"], cells["goal"]))
    n_zones = grid.get("n_zones")
    if n_zones is not None and n_zones > fit:
        raise SettingsError(
            f"grid.n_zones = {n_zones}: expected an integer from 0 to {fit} (the zones that fit the "
            f"{size} x {size} grid with this start and goal)"
        )
    if n_zones is None and zones_default > fit:
        raise SettingsError(
            f"grid.n_zones = None: the {layout} layout's {zones_default} zones do not fit the {size} x "
            f"{size} grid (at most {fit}); set grid.n_zones from 0 to {fit}, or a larger grid.size"
        )
