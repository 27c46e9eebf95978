"""recipes/tabular_gridworld.py runs end to end on two seeds and writes its table, json and figures."""

from __future__ import annotations

import json

import pytest

from tests.cli import run_command

pytestmark = pytest.mark.runs


def test_gridworld_recipe_end_to_end(tmp_path):
    cmd = [
        "recipes/tabular_gridworld.py",
        "seeds=[0,1]",
        "levels=[0.3,0.99]",
        "methods.thresholds=[0.0,1.0e-4]",
        "methods.demodice_alphas=[0.01,100.0]",
        "progress=false",
        f"hydra.run.dir={tmp_path}",
    ]
    proc = run_command(cmd)
    assert proc.returncode == 0, proc.stderr[-3000:]
    table = (tmp_path / "results.md").read_text()
    assert table.strip() in proc.stdout
    for row in (
        "| BC |",
        "| FBC |",
        "| DemoDICE |",
        "| SpoilDICE (Eq. 4) |",
        "| SpoilDICE (Eq. 6, lambda=100) |",
    ):
        assert row in table
    results = json.loads((tmp_path / "results.json").read_text())
    assert [r["seed"] for r in results["seeds"]] == [0, 1]
    assert set(results["summary"]) == {"safeness", "performance"}
    for seed in results["seeds"]:
        # 2 levels x 2 sweeps; the candidates hold every hyper-parameter of every method
        assert len(seed["problems"]) == 4
        for problem in seed["problems"]:
            assert len(problem["candidates"]["DemoDICE"]) == 2
            assert len(problem["candidates"]["FBC"]) == 2
            chosen = problem["selected"]["SpoilDICE (Eq. 6, lambda=100)"]
            assert chosen["normalised_cost"] == chosen["cost"] / 1e-4
        assert seed["route_lengths"]["shortest"] < seed["route_lengths"]["shortest_cost_free"]
        cmdp = seed["references"]["d*_Mc (CMDP optimum)"]
        assert abs(cmdp["normalised_return"] - 1.0) < 1e-12 and cmdp["normalised_cost"] <= 1.0 + 1e-6
    for png in ("layout.png", "tradeoff.png", "quality.png"):
        assert (tmp_path / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_gridworld_recipe_one_seed_has_no_standard_error(tmp_path):
    """With one seed the standard error is undefined (nan, as in spoil_torchrl.eval): the table prints the mean
    alone and results.json holds null."""
    cmd = [
        "recipes/tabular_gridworld.py",
        "seeds=[0]",
        "levels=[0.99]",
        "methods.thresholds=[0.0]",
        "methods.demodice_alphas=[1.0]",
        "methods.spoildice_lagrange=null",
        "grid.layout=along",
        "figures=false",
        "progress=false",
        f"hydra.run.dir={tmp_path}",
    ]
    proc = run_command(cmd, real=True)  # spoil-gridworld in a process of its own
    assert proc.returncode == 0, proc.stderr[-3000:]
    table = (tmp_path / "results.md").read_text()
    rows = [line for line in table.splitlines() if line.startswith("| ")]
    assert rows and not any("±" in line or "nan" in line for line in rows)
    assert "| BC | 1.000 / " in table and "Layout: `along`" in table
    results = json.loads((tmp_path / "results.json").read_text())
    entry = results["summary"]["safeness"]["0.99"]["BC"]
    assert entry["n"] == 1 and entry["return"][1] is None and entry["cost"][1] is None
    assert results["seeds"][0]["route_lengths"] == {"shortest": 20, "shortest_cost_free": 20}
