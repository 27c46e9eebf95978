"""The per-constraint table of a report, on results the test writes: each constraint's cost per method, the
share of episodes within every limit, and each cut's share of its own constraint's costly transitions."""

from __future__ import annotations

from spoil_torchrl.reporting.constraints import constraint_markdown


def _run(seed: int, cost_x: float, cost_y: float, leak: dict | None = None) -> dict:
    def evaluation(x, y):
        return {"cost": x + y, "cost_x": x, "cost_y": y, "feasible_all": float(x + y <= 25)}

    support = {"by_constraint": {"costly_kept": leak}} if leak else {}
    return {
        "seed": seed,
        "last_evaluations": 2,
        "evaluations": [evaluation(500.0, 500.0), evaluation(cost_x, cost_y), evaluation(cost_x + 2, cost_y)],
        "dice_diagnostics": {"support": support} if leak else None,
    }


def test_each_methods_constraint_costs_and_each_cuts_own_leak():
    runs = {
        ("walls", "spoildice"): [
            _run(0, 4.0, 10.0, {"x": {"x": 0.05, "y": 0.3}, "y": {"x": 0.3, "y": 0.07}}),
            _run(1, 8.0, 20.0, {"x": {"x": 0.07, "y": 0.2}, "y": {"x": 0.2, "y": 0.03}}),
        ],
        ("walls", "fbc"): [_run(0, 40.0, 0.0), _run(1, 60.0, 0.0)],
    }
    lines = constraint_markdown(runs).splitlines()
    assert lines[0] == "**walls**, per constraint"
    assert "| x cost | y cost | episodes within every limit | x cut keeps of x's costly |" in lines[2]
    fbc, spoildice = lines[4], lines[5]  # in the methods' order
    # the mean of the last two evaluations per seed (x: 41 and 61), then mean ± s.e. over seeds
    assert fbc.startswith("| FBC | 2 | 51.00 ± 10.00 | 51.00 ± 10.00 | 0.00 ± 0.00 | 0.00 ± 0.00 | - | - |")
    # SpoilDICE: x 5 and 9 per seed, y 10 and 20; within every limit 1 and 0 (seed 1 costs 29 and 28)
    assert spoildice.startswith("| SpoilDICE | 2 | 22.00 ± 7.00 | 7.00 ± 2.00 | 15.00 ± 5.00 | 0.50 ± 0.50 |")
    assert spoildice.endswith("| 6.0 ± 1.0 % | 5.0 ± 2.0 % |")  # the diagonal: each cut on its own constraint


def test_no_table_without_per_constraint_costs_or_with_differing_constraints():
    plain = {"seed": 0, "last_evaluations": 1, "evaluations": [{"cost": 3.0}]}
    assert constraint_markdown({("d", "bc"): [plain]}) is None
    other = _run(1, 1.0, 1.0)
    other["evaluations"] = [{"cost": 2.0, "cost_z": 2.0}]
    assert constraint_markdown({("d", "bc"): [_run(0, 1.0, 1.0), other]}) is None


def test_a_key_missing_from_part_of_the_averaged_window_is_left_out_and_one_seed_prints_its_mean():
    run = _run(0, 4.0, 10.0)
    del run["evaluations"][1]["feasible_all"]  # inside the last two evaluations the aggregate averages
    lines = constraint_markdown({("walls", "bc"): [run]}).splitlines()
    assert "episodes within every limit" not in lines[2]
    assert lines[4] == "| BC | 1 | 15.00 | 5.00 | 10.00 | - | - |"  # one seed: no standard error
