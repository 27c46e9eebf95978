"""A run's ``results.json`` and ``config.yaml``: written atomically, JSON-safe, and the paper's per-run aggregate.

The main recipe writes ``results.json`` after every evaluation (so an interrupted run keeps what it measured)
and ``config.yaml`` once, with the resolved settings; :func:`summary_table` is what it prints at the end.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from spoil_torchrl.eval.evaluator import METRICS
from spoil_torchrl.files import write_atomic

#: Settings left out of ``config.yaml``: how to start (``resume``) and which sweep the run is a cell of
#: (``experiment``, ``grid``: the cell's settings are the same in any sweep that has it, see
#: :func:`experiment_cell`); ``seeds`` is left out when unset (a seed of a ``seeds=[...]`` run has the settings
#: of the single-seed run of that seed, so the two compare and resume alike).
NOT_WRITTEN = ("resume", "experiment", "grid")


def _json_safe(value):
    """NaN / inf are not JSON: write them as null."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def write_json(path: Path, payload: dict) -> None:
    """Write ``payload`` atomically (a reader never sees half a file); NaN and inf become null.

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "results.json"
        >>> write_json(path, {"cost": float("nan"), "steps": [1, 2]})
        >>> json.loads(path.read_text())
        {'cost': None, 'steps': [1, 2]}
    """
    write_atomic(path, json.dumps(_json_safe(payload), indent=2, allow_nan=False))


def aggregate(evaluations: list[dict], last: int, keys: Sequence[str] = METRICS) -> dict:
    """The paper's per-run aggregate: each metric's (of ``keys``) mean over the last ``last`` evaluations.

    Examples:
        >>> runs = [{key: float(i) for key in METRICS} for i in range(4)]
        >>> aggregate(runs, 2)["normalized_cost"]
        2.5
    """
    tail = evaluations[-last:]
    return {key: sum(e[key] for e in tail) / len(tail) for key in keys}


def experiment_cell(cfg: DictConfig) -> dict | None:
    """Which cell of a paper experiment's sweep the run is (``experiment=...``): the experiment's name, the
    setting it varies (``level``, a dotted name, or ``None`` for a table) and that setting's value here; written
    into ``results.json``, where the experiment figures find it. ``None`` outside an experiment.

    Examples:
        >>> cfg = OmegaConf.create({"experiment": {"name": "fig4c", "level": "dataset.performance"},
        ...                         "dataset": {"performance": 0.25}})
        >>> experiment_cell(cfg)
        {'name': 'fig4c', 'level': 'dataset.performance', 'value': 0.25}
    """
    experiment = cfg.get("experiment")
    if experiment is None:
        return None
    level = experiment.get("level")
    value = None if level is None else OmegaConf.select(cfg, level, throw_on_missing=True)
    return {"name": str(experiment.name), "level": level, "value": value}


def settings_yaml(cfg: DictConfig) -> str:
    """The resolved settings as written to ``config.yaml`` (``resume`` left out: it says how to start, not what
    to train; ``seeds`` left out when null).

    Examples:
        >>> print(settings_yaml(OmegaConf.create({"seed": 1, "seeds": None, "resume": True})), end="")
        seed: 1
    """
    settings = OmegaConf.to_container(cfg, resolve=True)
    for key in NOT_WRITTEN:
        settings.pop(key, None)
    if settings.get("seeds", 0) is None:
        settings.pop("seeds")
    return OmegaConf.to_yaml(OmegaConf.create(settings))


def summary_table(results: dict) -> str:
    """The final evaluation and the aggregate of the main metrics, as markdown."""
    final = results["evaluations"][-1]
    lines = [
        f"{results['algo']} on {results['dataset']} (seed {results['seed']}), {final['step']} steps, "
        f"{results['total_seconds']:.0f} s",
        "",
        f"| metric | final evaluation | mean of last {results['last_evaluations']} |",
        "|---|---|---|",
    ]
    for key in ("normalized_feasible_return", "normalized_cost", "normalized_return", "return", "cost"):
        lines.append(f"| {key} | {final[key]:.3f} | {results['aggregate'][key]:.3f} |")
    return "\n".join(lines)


def note_where(
    results: dict, machine: dict, stage: str, from_step: int | None = None, **measured: float
) -> None:
    """Record in ``results["ran_on"]`` that ``stage`` (``"pre-training"`` or ``"main"``, the latter from step
    ``from_step``) ran on ``machine`` (:func:`~spoil_torchrl.stack.current_machine`), with what was
    ``measured`` of it (e.g. ``setup_seconds``: from the process's start to the main stage's), and set
    ``results["resumed_elsewhere"]`` once the run's parts have run on more than one CPU model (a report marks
    such runs: their numbers are exact continuations, but of arithmetic done on different CPUs).

    Examples:
        >>> results = {}
        >>> note_where(results, {"host": "a", "cpu": "x"}, "pre-training")
        >>> note_where(results, {"host": "a", "cpu": "x"}, "main", 0)
        >>> "resumed_elsewhere" in results
        False
        >>> note_where(results, {"host": "b", "cpu": "y"}, "main", 500)
        >>> results["resumed_elsewhere"], [part["stage"] for part in results["ran_on"]]
        (True, ['pre-training', 'main', 'main'])
    """
    part = {
        "stage": stage,
        **({} if from_step is None else {"from_step": int(from_step)}),
        **machine,
        **measured,
    }
    parts = results.setdefault("ran_on", [])
    parts.append(part)
    if len({p.get("cpu") for p in parts}) > 1:  # another host with the same CPU computes the same
        results["resumed_elsewhere"] = True
