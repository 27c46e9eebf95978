"""The committed run records under ``docs/results/`` are what a run writes, so that a sweep continued from them
(the cells copied into its ``hydra.sweep.dir``, ``resume=auto``) passes over them instead of refusing them."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import yaml

from spoil_torchrl.runs.results import NOT_WRITTEN
from spoil_torchrl.runs.resume import finished_already

RESULTS = Path(__file__).resolve().parents[2] / "docs" / "results"
# the offline runs (experts/ holds expert trainings, which record a config.json)
CELLS = sorted(
    p.parent for p in RESULTS.rglob("results.json") if "experts" not in p.relative_to(RESULTS).parts
)
Loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # a few hundred files: the C parser


@functools.cache
def _records() -> list[tuple[Path, str, dict, dict]]:
    out = []
    for cell in CELLS:
        config = (cell / "config.yaml").read_text()
        out.append(
            (cell, config, yaml.load(config, Loader=Loader), json.loads((cell / "results.json").read_text()))
        )
    return out


def test_every_committed_run_holds_its_own_resolved_settings():
    assert len(CELLS) > 100
    wrong = {}
    for cell, config, settings, results in _records():
        name = str(cell.relative_to(RESULTS))
        if "${" in config:
            wrong[name] = "Hydra's unresolved record (.hydra/config.yaml), not the run's config.yaml"
        elif set(NOT_WRITTEN) & set(settings):
            wrong[name] = f"keys a run leaves out of its config.yaml: {set(NOT_WRITTEN) & set(settings)}"
        elif (results["algo"], results["seed"]) != (settings["algo"]["name"], settings["seed"]):
            wrong[name] = "another run's settings"
    assert not wrong


def test_every_committed_experiment_cell_is_finished_and_passed_over_by_resume_auto():
    experiments = {}
    for cell, config, _, results in _records():
        if "experiment" in results:
            assert results["status"] == "finished", cell
            experiments.setdefault(results["experiment"]["name"], (cell, config, results))
    assert {"fig4c", "fig4d"} <= set(experiments)
    # one cell of each: settings_differ parses with OmegaConf, tens of milliseconds a file
    for cell, config, results in experiments.values():
        assert finished_already(cell, config, "auto") == results
