"""Experiment tracking: the TorchRL logger of a run, labelled and given the run's settings.

A run's logger (``logger=csv|tensorboard|wandb|mlflow|none``, built by TorchRL's
:func:`~torchrl.record.loggers.get_logger`) receives

* the resolved settings as hyper-parameters (``log_hparams``), flattened to dotted keys
  (``algo.name``, ``train.lr``, ``seed``) so that TensorBoard's HParams tab and W&B's run table can filter
  and group runs by any of them;
* a name, a project, a group and tags derived from the dataset, algorithm and seed
  (:func:`tracking_labels`), which W&B shows as columns and MLflow as the experiment name.

A logger whose package is missing is refused when the run starts (:func:`check_logger_available`), naming
the extra that installs it, not at the first logged value after minutes of pre-training.

Example:
    >>> flat_hparams({"algo": {"name": "spoildice", "hidden_cells": [256, 256]}, "seed": 0, "x": None})
    {'algo.name': 'spoildice', 'algo.hidden_cells': '[256, 256]', 'seed': 0, 'x': 'null'}
    >>> labels = tracking_labels({"algo": {"name": "bc"}, "dataset": {"name": "point-circle1-mixed"},
    ...                           "task": {"env_id": "SafetyPointCircle1-v0"}, "seed": 3, "logger": {}})
    >>> labels["name"], labels["group"]
    ('bc_point-circle1-mixed_seed3', 'point-circle1-mixed/bc')
    >>> labels["tags"]
    ['bc', 'point-circle1-mixed', 'SafetyPointCircle1-v0', 'seed3']
"""

from __future__ import annotations

import importlib.util
import json
import uuid
from collections.abc import Mapping
from pathlib import Path

from torchrl.record.loggers import Logger, get_logger

from spoil_torchrl.runs.settings import SettingsError

__all__ = [
    "LOGGER_PACKAGES",
    "check_logger_available",
    "flat_hparams",
    "make_logger",
    "tracking_labels",
]

#: logger type -> (the module it imports, what installs it)
LOGGER_PACKAGES = {
    "tensorboard": ("tensorboard", "pip install 'spoil_torchrl[tensorboard]'"),
    "wandb": ("wandb", "pip install 'spoil_torchrl[wandb]'"),
    "mlflow": ("mlflow", "pip install 'spoil_torchrl[mlflow]'"),
}
#: logger types that write nothing
NO_LOGGER = (None, "", "none")
DEFAULT_PROJECT = "spoil_torchrl"


def check_logger_available(kind: str | None, setting: str | None = None) -> None:
    """Refuse a logger type TorchRL does not know, or one whose package is not installed (a
    :class:`~spoil_torchrl.errors.SettingsError` saying what installs it). The messages name the main recipe's
    ``logger.type`` / ``logger=`` group, or ``setting`` where a recipe chooses its logger with another key.

    Examples:
        >>> check_logger_available("csv")
        >>> check_logger_available("nope", setting="logger.backend")
        Traceback (most recent call last):
        ...
        spoil_torchrl.errors.SettingsError: logger.backend='nope' is not a logger; choose one of csv, \
tensorboard, wandb, mlflow, none
    """
    if kind in NO_LOGGER or kind == "csv":
        return
    if kind not in LOGGER_PACKAGES:
        known = ", ".join(["csv", *LOGGER_PACKAGES, "none"])
        raise SettingsError(f"{setting or 'logger.type'}={kind!r} is not a logger; choose one of {known}")
    module, install = LOGGER_PACKAGES[kind]
    if importlib.util.find_spec(module) is None:
        raise SettingsError(
            f"{setting or 'logger'}={kind} needs the {module} package, which is not installed: {install} (or "
            f"choose {setting or 'logger'}=csv)"
        )


def flat_hparams(settings: Mapping, prefix: str = "") -> dict[str, int | float | str | bool]:
    """The settings as one level of dotted keys with scalar values (lists as JSON text, ``None`` as
    ``"null"``): the form TensorBoard's ``add_hparams`` and MLflow's ``log_params`` accept."""
    flat = {}
    for key, value in settings.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(flat_hparams(value, prefix=f"{name}."))
        elif isinstance(value, bool | int | float | str):
            flat[name] = value
        elif value is None:
            flat[name] = "null"
        else:
            flat[name] = json.dumps(list(value) if isinstance(value, tuple) else value)
    return flat


def tracking_labels(settings: Mapping) -> dict:
    """Name, project, group and tags of a run, from its resolved settings.

    ``logger.project`` / ``logger.group`` / ``logger.tags`` override the derived ones (the tags are added).
    """
    algo, dataset, seed = settings["algo"]["name"], settings["dataset"]["name"], settings["seed"]
    options = settings.get("logger") or {}
    tags = [algo, dataset, settings["task"]["env_id"], f"seed{seed}", *(options.get("tags") or [])]
    return {
        "name": f"{algo}_{dataset}_seed{seed}",
        "project": options.get("project") or DEFAULT_PROJECT,
        "group": options.get("group") or f"{dataset}/{algo}",
        "tags": tags,
    }


def make_logger(settings: Mapping, log_dir: Path, tracking: dict | None = None) -> tuple[Logger | None, dict]:
    """The run's TorchRL logger with its labels and hyper-parameters logged.

    Args:
        settings: the resolved settings (``OmegaConf.to_container(cfg, resolve=True)``).
        log_dir: where file-based loggers write (the run's ``logs/``).
        tracking: what a previous start of this run returned (``resume=true``), so that a resumed run
            continues the same W&B run rather than opening a new one.

    Returns:
        ``(logger, tracking)``: the logger (``None`` for ``logger=none``) and what to keep for a resume.
    """
    options = settings.get("logger") or {}
    kind = options.get("type")
    check_logger_available(kind)
    if kind in NO_LOGGER:
        return None, {}
    labels = tracking_labels(settings)
    tracking = dict(tracking or {})
    kwargs = {}
    if kind == "wandb":
        tracking.setdefault("wandb_id", uuid.uuid4().hex[:12])
        kwargs["wandb_kwargs"] = {
            "project": labels["project"],
            "group": labels["group"],
            "tags": labels["tags"],
            "id": tracking["wandb_id"],
            "offline": bool(options.get("offline", False)),
            "entity": options.get("entity"),
            "log_env_packages": False,
        }
    hparams = {key: value for key, value in settings.items() if key != "resume"}
    try:
        logger = get_logger(kind, logger_name=str(log_dir), experiment_name=labels["name"], **kwargs)
        logger.log_hparams(hparams if kind == "wandb" else flat_hparams(hparams))  # W&B filters nested keys
    except Exception as err:  # the service refused (no credentials, no network): before any training
        if kind != "wandb" or not type(err).__module__.startswith("wandb"):
            raise
        raise SettingsError(
            f"logger=wandb cannot start ({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}); "
            "log in (wandb login, or WANDB_API_KEY), or log offline (logger.offline=true), or choose logger=csv"
        ) from None
    return logger, tracking
