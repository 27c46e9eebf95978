"""Checking a run's settings before anything is loaded or trained, so a typo never costs a pre-training.

:func:`check_settings` walks the resolved configuration of the main recipe and checks every value whose
meaning is fixed by its name (learning rates, discount factors, quantiles, step counts, penalty coefficients,
layer sizes, ...) wherever it appears in ``train`` and ``algo``, the dataset's sizes and shares, the policy's
distribution (one the task's actions can take), and the top-level keys. Every problem is a
:class:`SettingsError` naming the dotted key, the value and what is expected.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

from spoil_torchrl.data.parallel import available_cores
from spoil_torchrl.data.prepare import SCHEMES
from spoil_torchrl.devices import training_device
from spoil_torchrl.errors import SettingsError
from spoil_torchrl.eval.dice_diagnostics import ALL_CUTS
from spoil_torchrl.modules.actor import CONTINUOUS_DISTRIBUTIONS, DISTRIBUTIONS
from spoil_torchrl.objectives.input_gradient import PENALTY_FORMS
from spoil_torchrl.precision import MATMUL_PRECISIONS
from spoil_torchrl.rules import (
    layers,
    non_negative,
    number,
    open_unit,
    optional,
    positive,
    positive_int,
    seed,
    switch,
    unit,
)
from spoil_torchrl.tasks import ENV_TASKS


def _penalty(value: Any) -> bool:  # a coefficient, or one per role
    return non_negative(value) or (
        isinstance(value, Mapping) and all(non_negative(v) for v in value.values())
    )


#: key name -> (check, what is expected); applies wherever the key appears in ``train`` or ``algo``.
RULES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "lr": (positive, "a finite number > 0"),
    "gamma": (open_unit, "a number in (0, 1)"),
    "kappa": (open_unit, "a quantile in (0, 1)"),
    "eta": (open_unit, "a class prior in (0, 1)"),
    "steps": (positive_int, "an integer >= 1"),
    "discriminator_steps": (positive_int, "an integer >= 1"),
    "eval_interval": (positive_int, "an integer >= 1"),
    "eval_episodes": (positive_int, "an integer >= 1"),
    "last_evaluations": (positive_int, "an integer >= 1"),
    "batch_size": (positive_int, "an integer >= 1"),
    "log_interval": (positive_int, "an integer >= 1"),
    "update_interval": (positive_int, "an integer >= 1"),
    "gradient_penalty": (_penalty, "a number >= 0 (or one per role)"),
    "nu_gradient_penalty": (_penalty, "a number >= 0"),
    "hidden_cells": (layers, "a list of layer sizes >= 1"),
    "init_lagrange": (number, "a finite number"),
    "compile": (switch, "true or false"),
    "checkpoint": (switch, "true or false"),
    "reference_offsets": (switch, "true or false"),
    "standardize_reward": (switch, "true or false"),
    "matmul_precision": (lambda v: v in MATMUL_PRECISIONS, " | ".join(MATMUL_PRECISIONS)),
    "penalty_form": (lambda v: v in PENALTY_FORMS, " | ".join(PENALTY_FORMS)),
    "alpha": (
        lambda v: v == "auto" or non_negative(v),
        "a number >= 0 (or auto where the algorithm allows)",
    ),
}


#: key name -> (check, what is expected) for the ``dataset`` section.
DATASET_RULES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "n_safe": (positive_int, "an integer >= 1"),
    "n_performant": (positive_int, "an integer >= 1"),
    "n_unlabeled": (optional(positive_int), "null or an integer >= 1"),
    "n_nonpreferred": (optional(positive_int), "null or an integer >= 1"),
    "performance": (unit, "a share in [0, 1]"),
    "safeness": (unit, "a share in [0, 1]"),
    "return_quantile": (unit, "a quantile in [0, 1]"),
    "cost_threshold": (optional(non_negative), "null or a number >= 0"),
    "scheme": (lambda v: v in SCHEMES, " or ".join(SCHEMES)),
    "generate": (switch, "true or false"),
    "constraints": (
        lambda v: (
            v is None
            or (
                isinstance(v, (list, tuple))
                and len(v) >= 1
                and len(set(v)) == len(v)
                and all(isinstance(n, str) and n.isidentifier() and n != ALL_CUTS for n in v)
            )
        ),
        f"null or a list of distinct constraint names (the data's cost_<name> components; not {ALL_CUTS!r}, "
        "which names the whole support in the diagnostics)",
    ),
    "n_safe_per_constraint": (optional(positive_int), "null or an integer >= 1"),
    "constraint_pools": (
        lambda v: v is None or (isinstance(v, Mapping) and all(isinstance(x, str) for x in v.values())),
        "null or a mapping of constraint names to typed pools of the file",
    ),
    "constraint_thresholds": (
        lambda v: v is None or (isinstance(v, Mapping) and all(non_negative(x) for x in v.values())),
        "null or a mapping of constraint names to thresholds >= 0",
    ),
    "return_range": (
        lambda v: (
            v is None
            or (isinstance(v, (list, tuple)) and len(v) == 2 and all(map(number, v)) and v[0] < v[1])
        ),
        "null or two finite numbers [R_min, R_max] with R_min < R_max",
    ),
}

#: The algorithms that take ``dataset.constraints`` (several safety constraints, one safe set each).
CONSTRAINED_ALGORITHMS = ("spoildice", "fbc")

#: Top-level and nested settings that are switches. Hydra keeps ``no`` / ``off`` / ``0`` as they are typed
#: (a string, an integer), and a string is always true, so anything but true or false is refused.
SWITCHES = ("normalize_observations", "progress", "force", "eval.frames")


def _dotted(cfg: Mapping, name: str) -> tuple[bool, Any]:
    node: Any = cfg
    for part in name.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return False, None
        node = node[part]
    return True, node


def _rule(key: str) -> tuple[Callable[[Any], bool], str] | None:
    if key in RULES:
        return RULES[key]
    if key.endswith("_lr"):
        return RULES["lr"]
    return None


def _walk(tree: Mapping, prefix: str):
    for key, value in tree.items():
        name = f"{prefix}.{key}"
        if isinstance(value, Mapping) and key not in ("gradient_penalty",):
            yield from _walk(value, name)
        else:
            yield name, str(key), value


def check_settings(cfg: Mapping[str, Any]) -> None:
    """Raise :class:`SettingsError` for the first setting of ``cfg`` (a resolved mapping) that cannot be right.

    Examples:
        >>> check_settings({"seed": 0, "threads": 1, "train": {"lr": 3e-4}, "algo": {"kappa": 0.01}})
        >>> check_settings({"seed": 0, "threads": 1, "train": {"lr": 3e-4}, "algo": {"kappa": 1.5}})
        Traceback (most recent call last):
        ...
        spoil_torchrl.errors.SettingsError: algo.kappa = 1.5: expected a quantile in (0, 1)
        >>> check_settings({"seeds": [0, 1, 1]})
        Traceback (most recent call last):
        ...
        spoil_torchrl.errors.SettingsError: seeds = [0, 1, 1]: expected null or a list of distinct integers >= 0
    """
    cores = available_cores()
    for key, check, expected in (
        ("seed", seed, "an integer >= 0"),
        (
            "threads",
            lambda v: positive_int(v) and v <= cores,
            f"an integer from 1 to {cores} (this machine's cores)",
        ),
        ("task.eval_num_envs", positive_int, "an integer >= 1"),
        *((key, switch, "true or false") for key in SWITCHES),
    ):
        present, value = _dotted(cfg, key)
        if present and not check(value):
            raise SettingsError(f"{key} = {value!r}: expected {expected}")
    present, device = _dotted(cfg, "device")
    if present:
        training_device(device)  # a name torch knows, of a device this machine has
    seeds = cfg.get("seeds")
    if seeds is not None and not (
        isinstance(seeds, (list, tuple))
        and seeds
        and all(seed(s) for s in seeds)
        and len(set(seeds)) == len(seeds)
    ):
        raise SettingsError(f"seeds = {seeds!r}: expected null or a list of distinct integers >= 0")
    # seed's default (0) is there whatever was asked; another seed beside seeds=[...] would be ignored
    if seeds is not None and cfg.get("seed", 0) not in (0, *seeds):
        raise SettingsError(
            f"seed = {cfg['seed']!r} with seeds = {list(seeds)!r}: a seeds=[...] run trains exactly those seeds; "
            "leave seed out, or add it to seeds"
        )
    for section in ("train", "algo"):
        if not isinstance(cfg.get(section), Mapping):
            continue
        for name, key, value in _walk(cfg[section], section):
            rule = _rule(key)
            if rule is not None and not rule[0](value):
                raise SettingsError(f"{name} = {value!r}: expected {rule[1]}")
    for key, value in (cfg.get("dataset") or {}).items():
        rule = DATASET_RULES.get(key)
        if rule is not None and not rule[0](value):
            raise SettingsError(f"dataset.{key} = {value!r}: expected {rule[1]}")
    _, evaluated = _dotted(cfg, "eval.constraints")
    if evaluated is not None and not DATASET_RULES["constraints"][0](evaluated):
        raise SettingsError(f"eval.constraints = {evaluated!r}: expected a list of distinct constraint names")
    _, constraints = _dotted(cfg, "dataset.constraints")
    if constraints and evaluated and sorted(constraints) != sorted(evaluated):
        raise SettingsError(
            f"eval.constraints = {list(evaluated)!r} differs from dataset.constraints = {list(constraints)!r}: a run "
            "is evaluated on the constraints it trains with; set one of them"
        )
    _check_distribution(cfg)
    _, algo = _dotted(cfg, "algo.name")
    if constraints and algo not in CONSTRAINED_ALGORITHMS:
        raise SettingsError(
            f"dataset.constraints = {list(constraints)!r}: several constraints are taken by algo="
            f"{' | '.join(CONSTRAINED_ALGORITHMS)} only (one support cut per constraint); algo={algo} would "
            "ignore them (docs/several_constraints.md)"
        )
    for key in (
        ("init_lagrange", "init_tau") if algo == "coptidice" else ()
    ):  # COptiDICE learns their logarithms
        present, value = _dotted(cfg, f"algo.{key}")
        if present and not (number(value) and value > 0):
            raise SettingsError(
                f"algo.{key} = {value!r}: COptiDICE learns its logarithm; expected a finite number > 0"
            )


def _check_distribution(cfg: Mapping[str, Any]) -> None:
    """Refuse an ``algo.distribution`` :func:`~spoil_torchrl.modules.make_actor` does not offer, and one of
    discrete actions for a simulated task: every task of :data:`~spoil_torchrl.tasks.ENV_TASKS` acts in a box
    of continuous actions (``action_dim`` coordinates in ``[-action_bound, action_bound]``), where a one-hot
    ``categorical`` policy trains and evaluates to numbers that mean nothing. (A task the table does not know
    is left to the task lookup.)

    Examples:
        >>> task, algo = {"env_id": "SafetyPointCircle1-v0"}, {"distribution": "categorical"}
        >>> check_settings({"task": task, "algo": algo})
        Traceback (most recent call last):
        ...
        spoil_torchrl.errors.SettingsError: algo.distribution = 'categorical': SafetyPointCircle1-v0's \
actions are continuous (2 coordinates in [-1, 1]); expected tanh_normal | normal
    """
    present, distribution = _dotted(cfg, "algo.distribution")
    _, env_id = _dotted(cfg, "task.env_id")
    task = ENV_TASKS.get(env_id) if isinstance(env_id, str) else None
    accepted = DISTRIBUTIONS if task is None else CONTINUOUS_DISTRIBUTIONS
    if present and distribution not in accepted:
        why = ""
        if distribution in DISTRIBUTIONS:  # offered, but not for this task's actions
            bound = f"[-{task.action_bound:g}, {task.action_bound:g}]"
            why = f"{env_id}'s actions are continuous ({task.action_dim} coordinates in {bound}); "
        raise SettingsError(f"algo.distribution = {distribution!r}: {why}expected {' | '.join(accepted)}")


def name_dataset_by_source(cfg, overrides: Sequence[str]) -> None:
    """Set ``dataset.name`` from ``dataset.source`` (:func:`~spoil_torchrl.data.prepare.source_name`) when the
    command line set the source but not the name: the name is what runs are filed and reported under, and the
    dataset config's own name belongs to its own source.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"dataset": {"name": "point-circle1-mixed", "source": "file:/d/noisy.hdf5"}})
        >>> name_dataset_by_source(cfg, ["dataset.source=file:/d/noisy.hdf5"])
        >>> cfg.dataset.name
        'noisy'
    """
    from omegaconf import open_dict

    from spoil_torchrl.data.prepare import source_name

    keys = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
    if "dataset.source" in keys and "dataset.name" not in keys and "dataset" not in keys:
        with open_dict(cfg):
            cfg.dataset.name = source_name(str(cfg.dataset.source))
