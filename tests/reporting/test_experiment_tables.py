"""A paper experiment's cells read back from run directories: grouping, refusals, tables and score matrices."""

from __future__ import annotations

import json

import pytest

from spoil_torchrl.eval.experiment_tables import (
    experiment_markdown,
    level_summary,
    score_matrices,
    task_average,
)
from spoil_torchrl.reporting.experiments import load_experiment
from tests.cli import run_command


def _cell(root, dataset, value, algo, seed, ret, cost, *, name="fig4c", level="dataset.performance", **extra):
    run = root / dataset / f"performance{value}" / algo / f"seed{seed}"
    run.mkdir(parents=True)
    results = {
        "dataset": dataset,
        "algo": algo,
        "seed": seed,
        "status": "finished",
        "experiment": {"name": name, "level": level, "value": value},
        "aggregate": {"normalized_feasible_return": ret, "normalized_cost": cost},
        **extra,
    }
    (run / "results.json").write_text(json.dumps(results))
    (run / "config.yaml").write_text("train:\n  steps: 10\n")
    return run


def _grid(root):
    # two tasks, two levels, two methods, two seeds; SpoilDICE better and safe everywhere
    for dataset, offset in (("a", 0.0), ("b", 0.1)):
        for value in (0.25, 0.75):
            for seed in (0, 1):
                _cell(root, dataset, value, "bc", seed, 0.2 + offset + 0.1 * seed, 3.0 + seed)
                _cell(root, dataset, value, "spoildice", seed, 0.6 + offset + 0.1 * seed, 0.2)


def test_cells_group_by_task_level_and_method(tmp_path):
    _grid(tmp_path)
    _cell(tmp_path, "a", 0.5, "bc", 0, 0.0, 0.0, status="training")  # not finished: left out, reported
    skipped = []
    experiment = load_experiment([tmp_path], skipped=skipped)
    assert experiment.name == "fig4c" and experiment.level == "dataset.performance"
    assert experiment.datasets == ["a", "b"] and experiment.levels == [0.25, 0.75]
    assert experiment.algos == ["bc", "spoildice"]  # the paper's order
    assert len(skipped) == 1 and skipped[0][1] == "killed"
    summary = level_summary(experiment.cells)
    # bc on a at 0.25: seeds 0.2 and 0.3 -> mean 0.25, s.e. = std(ddof=1) / sqrt(2) = 0.0707 / 1.414 = 0.05
    mean, se = summary[("a", 0.25, "bc")]["normalized_feasible_return"]
    assert mean == pytest.approx(0.25) and se == pytest.approx(0.05)
    # averaged over tasks a (0.25) and b (0.35): 0.30, s.e. sqrt(0.05^2 + 0.05^2) / 2 = 0.0354
    mean, se = task_average(summary)[(0.25, "bc")]["normalized_feasible_return"]
    assert mean == pytest.approx(0.30) and se == pytest.approx(0.05 * 2**0.5 / 2)
    text = experiment_markdown(experiment)
    assert "| normalised feasible return | 0.25 | 0.75 |" in text and "**average over 2 tasks**" in text
    assert "| SpoilDICE | **0.70 ± 0.04** | **0.70 ± 0.04** |" in text  # safe: bold
    assert "| BC | 0.30 ± 0.04 | 0.30 ± 0.04 |" in text
    assert "**a**" in text and "**b**" in text  # and one table per task


def test_cells_resumed_on_another_machine_are_named(tmp_path):
    _grid(tmp_path)
    moved = _cell(tmp_path, "a", 0.5, "bc", 0, 0.2, 3.0, resumed_elsewhere=True)
    assert load_experiment([tmp_path]).resumed_elsewhere == [str(moved)]


def test_score_matrices_hold_the_seeds_every_task_has(tmp_path):
    _grid(tmp_path)
    _cell(tmp_path, "a", 0.25, "bc", 2, 0.9, 0.0)  # a third seed on one task only
    experiment = load_experiment([tmp_path])
    scores = score_matrices(experiment, "normalized_feasible_return", 0.25)
    assert scores["bc"].shape == (2, 2)  # seeds 0 and 1 on tasks a, b
    assert scores["bc"].tolist() == [[0.2, 0.30000000000000004], [0.30000000000000004, 0.4]]
    pooled = score_matrices(experiment, "normalized_feasible_return", over_levels=True)
    assert pooled["spoildice"].shape == (2, 4)  # (a, b) x (0.25, 0.75)


def test_mixed_cells_are_refused(tmp_path):
    _grid(tmp_path / "one")
    _cell(tmp_path / "one", "a", 0.25, "fbc", 0, 0.5, 0.5, name="fig4d", level="dataset.safeness")
    with pytest.raises(ValueError, match="several experiments under .*: fig4c, fig4d; name one"):
        load_experiment([tmp_path / "one"])
    assert load_experiment([tmp_path / "one"], name="fig4d").algos == ["fbc"]
    _grid(tmp_path / "two")
    with pytest.raises(ValueError, match="seed 0 of bc at dataset.performance=0.25 on a twice"):
        load_experiment([tmp_path / "one", tmp_path / "two"], name="fig4c")
    other = _cell(tmp_path / "three", "a", 0.25, "bc", 0, 0.5, 0.5)
    _cell(tmp_path / "three", "a", 0.75, "bc", 0, 0.5, 0.5)
    (other / "config.yaml").write_text("train:\n  steps: 20\n")
    with pytest.raises(ValueError, match="different train settings"):
        load_experiment([tmp_path / "three"])
    with pytest.raises(ValueError, match="no finished cell of experiment 'fig4a'"):
        load_experiment([tmp_path / "three"], name="fig4a")
    with pytest.raises(FileNotFoundError):
        load_experiment([tmp_path / "missing"])


def test_a_setting_older_runs_did_not_write_reads_as_their_value(tmp_path):
    _grid(tmp_path)  # written without train.penalty_form: autograd's, as a resumed run reads them
    stated = _cell(tmp_path, "a", 0.25, "fbc", 0, 0.5, 0.5)
    (stated / "config.yaml").write_text("train:\n  steps: 10\n  penalty_form: autograd\n")
    assert load_experiment([tmp_path]).algos == ["bc", "fbc", "spoildice"]
    (stated / "config.yaml").write_text("train:\n  steps: 10\n  penalty_form: relu_chain\n")
    with pytest.raises(ValueError, match="different train settings"):
        load_experiment([tmp_path])


def test_statistics_name_the_improvement_over_each_baseline(tmp_path):
    pytest.importorskip("rliable")
    from spoil_torchrl.eval.experiment_tables import experiment_statistics

    _grid(tmp_path)
    text = experiment_statistics(load_experiment([tmp_path]), reps=50)
    # SpoilDICE beats BC in every run of every task and level: P = 1 with a collapsed interval
    assert "| BC | 1.00 [1.00, 1.00] |" in text
    assert "| SpoilDICE | 0.70 [" in text  # its IQM over 2 seeds x 2 tasks at each level: (0.6+0.7+0.7+0.8)/4


def test_a_sweep_still_running_reports_what_it_has(tmp_path):
    """Task b has no cell at level 0.75 yet: its tables show "-" there and the statistics skip that level."""
    pytest.importorskip("rliable")
    from spoil_torchrl.eval.experiment_tables import experiment_statistics

    for dataset, value in (("a", 0.25), ("a", 0.75), ("b", 0.25)):
        for seed in (0, 1):
            _cell(tmp_path, dataset, value, "spoildice", seed, 0.5 + 0.1 * seed, 0.5)
    experiment = load_experiment([tmp_path])
    text = experiment_statistics(experiment, reps=20)
    assert "| SpoilDICE | 0.55 [0.50, 0.60] | - |" in text  # 0.75: no method has both tasks
    assert "| SpoilDICE | **0.55 ± 0.05** | - |" in experiment_markdown(experiment)  # the average over tasks


def test_dice_diagnostics_are_tabulated_per_task_method_and_level(tmp_path):
    """Mean over seeds in percent with the seeds' range; a level whose runs lack a diagnostic shows "-", a
    method without weights (BC) has no table, and ``spoil-report --figure`` writes the tables."""
    from spoil_torchrl.eval.experiment_tables import diagnostics_markdown

    for value in (0.25, 0.75):
        for seed, kept in enumerate((0.10, 0.15, 0.50)):  # mean 25, not the range's midpoint 30
            weights = {
                "role": "unlabeled",
                "support": {"kept": kept} if value == 0.25 else {},
                "weight_share": {"cost>0": {"weight": 0.01 * (seed + 1), "transitions": 0.2}},
                "effective_sample_size": float("nan") if value == 0.25 else True,  # no numbers: left out
            }
            _cell(tmp_path, "a", value, "spoildice", seed, 0.6, 0.2, dice_diagnostics=weights)
            _cell(tmp_path, "a", value, "bc", seed, 0.3, 3.0, dice_diagnostics=None)
    text = diagnostics_markdown(load_experiment([tmp_path]))
    assert text.count("DICE diagnostics") == 1
    assert "**a, SpoilDICE: DICE diagnostics, weights on unlabeled**" in text
    assert "| support: share of D_U kept | 25.0 [10.0, 50.0] | - |" in text
    assert "| weight mass on transitions with a cost | 2.0 [1.0, 3.0] | 2.0 [1.0, 3.0] |" in text
    assert "effective sample size" not in text and "nan" not in text
    assert diagnostics_markdown(load_experiment([tmp_path / "a" / "performance0.25" / "bc"])) == ""

    report = run_command(["recipes/report.py", "--figure", tmp_path, "--out", tmp_path / "fig.md"])
    assert report.returncode == 0, report.stderr
    assert "| support: share of D_U kept | 25.0 [10.0, 50.0] | - |" in (tmp_path / "fig.md").read_text()


def test_cells_of_one_dataset_from_two_stacks_or_two_files_are_refused(tmp_path):
    _cell(tmp_path / "s", "a", 0.25, "bc", 0, 0.5, 0.5, stack={"mujoco": "2.3.7"})
    _cell(tmp_path / "s", "a", 0.75, "bc", 0, 0.5, 0.5, stack={"mujoco": "3.17.0"})
    with pytest.raises(ValueError, match="made on 2 software stacks"):
        load_experiment([tmp_path / "s"])
    _cell(tmp_path / "f", "a", 0.25, "bc", 0, 0.5, 0.5, data={"fingerprint": "x"})
    _cell(tmp_path / "f", "a", 0.75, "bc", 0, 0.5, 0.5, data={"fingerprint": "y"})
    with pytest.raises(ValueError, match="trained on different data.*--mixed-files"):
        load_experiment([tmp_path / "f"])
    # let in on request, counted, and said beside the tables
    _cell(tmp_path / "f", "a", 0.75, "bc", 1, 0.5, 0.5, data={"fingerprint": "y"})
    experiment = load_experiment([tmp_path / "f"], mixed_files=True)
    assert experiment.files == {"a": {"x": 1, "y": 2}}
    assert (
        "a: the runs were trained on 2 files of this dataset (`x`: 1 runs, `y`: 2 runs)."
        in experiment_markdown(experiment)
    )
    with pytest.raises(ValueError, match="made on 2 software stacks"):
        load_experiment([tmp_path / "s"], mixed_files=True)
