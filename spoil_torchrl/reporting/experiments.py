"""A paper experiment read back from its cells' run directories.

A run started by ``experiment=<name>`` (``configs/experiment/``) records its cell in ``results.json``
(``experiment``: the experiment's name, the setting it varies and that setting's value). :func:`load_experiment`
collects the finished cells of one experiment from any folders into an
:class:`~spoil_torchrl.eval.experiment_tables.Experiment`, refusing what would mix results that do not belong
together (two runs of one cell and seed, two training budgets, two software stacks or data files of one
dataset); :mod:`spoil_torchrl.eval.experiment_tables` makes its tables, figure panels and statistics.
"""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Iterator, Sequence
from pathlib import Path

from spoil_torchrl.eval.experiment_tables import Experiment
from spoil_torchrl.runs.directory import run_status


def train_section(results_path: Path) -> str | None:
    """The ``train:`` section (the training budget) of the ``config.yaml`` beside a run's ``results.json``, as
    YAML (``None`` when the run folder has none): runs of one table must share it. A setting that older versions
    did not write reads as the value their runs had (:data:`~spoil_torchrl.runs.resume.IMPLIED_SETTINGS`, e.g.
    ``train.penalty_form: autograd``), as when such a run is resumed, so a sweep that continues committed cells
    with that value stated reports with them.

    Examples:
        >>> import tempfile
        >>> folder = Path(tempfile.mkdtemp())
        >>> _ = (folder / "config.yaml").write_text("train:\\n  steps: 10\\n")
        >>> print(train_section(folder / "results.json"), end="")
        penalty_form: autograd
        steps: 10
    """
    from omegaconf import OmegaConf

    from spoil_torchrl.runs.resume import IMPLIED_SETTINGS

    config = results_path.parent / "config.yaml"
    if not config.is_file():
        return None
    train = OmegaConf.load(config).get("train")
    if train is None:
        return None
    section = OmegaConf.to_container(train)
    for key, value in IMPLIED_SETTINGS.items():
        if key.startswith("train."):
            section.setdefault(key.removeprefix("train."), value)
    return OmegaConf.to_yaml(dict(sorted(section.items())))


#: What every finished run of ``recipes/spoildice_dsrl.py`` records in its ``results.json`` and the report
#: reads (an expert's run, ``recipes/train_experts.py``, records none of it).
RUN_KEYS = ("dataset", "algo", "seed", "aggregate", "evaluations", "total_seconds")
#: What the tables of an experiment's cells read (:func:`load_experiment`), besides ``experiment``.
CELL_KEYS = ("dataset", "algo", "seed", "aggregate")


def incomplete(results: dict, keys: tuple[str, ...] = RUN_KEYS) -> str | None:
    """Why a finished run's ``results.json`` cannot be reported (the ``keys`` it lacks, or an ``aggregate``
    that is not a mapping), ``None`` when it can.

    Examples:
        >>> results = {"status": "finished", "dataset": "d", "algo": "bc", "seed": 0}
        >>> print(incomplete(results))  # doctest: +ELLIPSIS
        finished, but its results.json has no aggregate, evaluations, total_seconds (not a run of recipes/...)
        >>> incomplete({"dataset": "d", "algo": "bc", "seed": 0, "aggregate": {}, "evaluations": [],
        ...             "total_seconds": 1.0}) is None
        True
    """
    missing = [key for key in keys if key not in results]
    if missing:
        return (
            f"finished, but its results.json has no {', '.join(missing)} (not a run of "
            "recipes/spoildice_dsrl.py?)"
        )
    if not isinstance(results["aggregate"], dict):
        return f"finished, but its results.json's aggregate is not a mapping: {results['aggregate']!r}"
    return None


def finished_results(folders: Sequence[str | Path], skipped: list) -> Iterator[tuple[Path, dict]]:
    """``(path, results)`` of every finished run's ``results.json`` under ``folders``, sorted per folder; the
    others are appended to ``skipped`` as ``(path, reason)`` (unreadable, not a JSON object, without a
    ``status``, or their status and error).

    Raises:
        FileNotFoundError: a folder does not exist.
    """
    for folder in map(Path, folders):
        if not folder.exists():
            raise FileNotFoundError(f"{folder}: no such folder")
        for path in sorted(folder.rglob("results.json")):
            try:
                results = json.loads(path.read_text())
            except (OSError, ValueError) as err:
                skipped.append((path, f"unreadable ({err})"))
                continue
            if not isinstance(results, dict):
                kind = {list: "a list", str: "a string", bool: "true or false", type(None): "null"}
                held = kind.get(type(results), "a number")
                skipped.append(
                    (path, f"not a run's results: its results.json holds {held}, not a JSON object")
                )
                continue
            if "status" not in results:
                skipped.append((path, "no status in its results.json (not a run's results?)"))
                continue
            status = run_status(path.parent, results)
            if status != "finished":
                error = results.get("error")  # a diverged or crashed run says why it failed
                skipped.append((path, status if error is None else f"{status} ({error})"))
                continue
            yield path, results


def load_experiment(
    folders: Sequence[str | Path],
    *,
    name: str | None = None,
    skipped: list | None = None,
    mixed_files: bool = False,
) -> Experiment:
    """The finished cells of experiment ``name`` (the only one found when ``None``) under ``folders``.

    Runs that did not finish are appended to ``skipped`` as ``(path, reason)``, as are runs of no experiment.
    ``mixed_files``: cells of one dataset may come from different files of it (``Experiment.files`` counts
    them, and :func:`experiment_markdown` says so): a generated dataset made again on another CPU is another
    file, its episodes rounded differently, though made by the same policies from the same seeds.

    Raises:
        FileNotFoundError: a folder does not exist.
        ValueError: no finished cell; several experiments and no ``name``; one cell's seed twice; cells of one
            experiment with different levels or training budgets (``config.yaml``'s ``train``), or cells of one
            dataset made on different software stacks or from different data.
    """
    skipped = [] if skipped is None else skipped
    found: dict[str, list[tuple[Path, dict]]] = defaultdict(list)
    for path, results in finished_results(folders, skipped):
        if incomplete(results, CELL_KEYS) is not None:
            skipped.append((path, incomplete(results, CELL_KEYS)))
        elif "experiment" not in results:
            skipped.append((path, "not a cell of an experiment (started without experiment=...)"))
        else:
            found[results["experiment"]["name"]].append((path, results))
    where = ", ".join(map(str, folders))
    if name is None:
        if len(found) > 1:
            raise ValueError(
                f"cells of several experiments under {where}: {', '.join(sorted(found))}; name one"
            )
        if not found:
            raise ValueError(f"no finished cell of an experiment under {where}")
        name = next(iter(found))
    if name not in found:
        raise ValueError(f"no finished cell of experiment {name!r} under {where}")
    experiment = _cells(name, found[name], mixed_files=mixed_files)
    experiment.unfinished = [
        (str(p.parent), reason)
        for p, reason in skipped
        if not reason.startswith(("not a cell", "finished, but"))
    ]
    return experiment


def _cells(name: str, runs: list[tuple[Path, dict]], *, mixed_files: bool = False) -> Experiment:
    levels = {r["experiment"]["level"] for _, r in runs}
    if len(levels) > 1:
        raise ValueError(f"the cells of {name} vary different settings: {sorted(map(str, levels))}")
    budgets: dict[str | None, Path] = {}
    seen: dict[tuple, Path] = {}
    stacks: dict[str, dict[str, Path]] = defaultdict(dict)
    files: dict[str, tuple[str, Path]] = {}
    experiment = Experiment(name, levels.pop())
    for path, results in runs:
        # one dataset's cells come from one simulator: the software stack the run recorded
        stacks[results["dataset"]].setdefault(json.dumps(results.get("stack"), sort_keys=True), path)
        fingerprint = (results.get("data") or {}).get(
            "fingerprint"
        )  # the file's episodes, whatever the roles
        if fingerprint is not None:
            first = files.setdefault(results["dataset"], (fingerprint, path))
            counts = experiment.files.setdefault(results["dataset"], {})
            counts[fingerprint] = counts.get(fingerprint, 0) + 1
            if first[0] != fingerprint and not mixed_files:
                raise ValueError(
                    f"the cells of {name} filed as {results['dataset']} were trained on different data: "
                    f"{first[1].parent} and {path.parent}; give each file its own dataset.name (or, for "
                    "one dataset made again elsewhere, e.g. on another CPU, let its files share the tables: "
                    "--mixed-files)"
                )
        if results.get("resumed_elsewhere"):
            experiment.resumed_elsewhere.append(str(path.parent))
        key = (results["dataset"], results["experiment"]["value"], results["algo"])
        if (*key, results["seed"]) in seen:
            raise ValueError(
                f"seed {results['seed']} of {key[2]} at {experiment.level}={key[1]} on {key[0]} twice: "
                f"{seen[(*key, results['seed'])].parent} and {path.parent}"
            )
        seen[(*key, results["seed"])] = path
        budgets.setdefault(train_section(path), path)
        experiment.cells.setdefault(key, []).append(results)
    for dataset, made_on in stacks.items():
        if len(made_on) > 1:
            raise ValueError(
                f"the cells of {name} on {dataset} were made on {len(made_on)} software stacks (other simulators), "
                "e.g. "
                + " and ".join(str(p.parent) for p in made_on.values())
                + "; report each stack's cells apart"
            )
    if len(budgets) > 1:
        raise ValueError(
            f"the cells of {name} were trained with different train settings, e.g. "
            + " and ".join(str(p.parent) for p in budgets.values())
        )
    for group in experiment.cells.values():
        group.sort(key=lambda r: r["seed"])
    return experiment
