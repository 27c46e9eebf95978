"""Every method through the main recipe (``preset=smoke``, in this process): one run per algorithm for the
module, and each test below reads what it checks from those runs. ``tests/test_recipes.py`` runs the compiled
SpoilDICE end to end with the logger and the DICE diagnostics."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from spoil_torchrl.algorithms import ALGORITHMS
from tests.cli import Ran, run_command

pytestmark = pytest.mark.runs

ALGOS = list(ALGORITHMS)
#: what a run of one method changes from the others' settings, to cover another path of the recipe
EXTRA = {"bc": ["normalize_observations=false"]}


class SmokeRun:
    def __init__(self, algo: str, ran: Ran, run_dir: Path):
        self.algo, self.ran, self.dir = algo, ran, run_dir
        self.results = json.loads((run_dir / "results.json").read_text())


@pytest.fixture(scope="module")
def smoke(tmp_path_factory, tiny_pc1_dataset):
    """``smoke(algo)``: the module's run of ``algo`` (made at its first use)."""
    runs: dict[str, SmokeRun] = {}

    def run(algo: str) -> SmokeRun:
        if algo not in runs:
            run_dir = tmp_path_factory.mktemp(f"smoke-{algo}")
            ran = run_command(
                [
                    "recipes/spoildice_dsrl.py",
                    "preset=smoke",
                    "train.batch_size=64",  # the plumbing, at a quarter of the preset's update cost
                    f"algo={algo}",
                    "logger=none",
                    "progress=false",
                    f"dataset.source=file:{tiny_pc1_dataset}",
                    "dataset.n_safe=2",
                    "dataset.n_performant=2",
                    f"hydra.run.dir={run_dir}",
                    *EXTRA.get(algo, []),
                ]
            )
            assert ran.returncode == 0, ran.stderr[-3000:]
            runs[algo] = SmokeRun(algo, ran, run_dir)
        return runs[algo]

    return run


@pytest.mark.parametrize("algo", ALGOS)
def test_a_run_finishes_with_an_evaluation_at_every_interval(smoke, algo):
    run = smoke(algo)
    results = run.results
    assert results["status"] == "finished" and results["algo"] == algo and results["seed"] == 0
    assert (
        results["update_step"] == "eager" and results["matmul_precision"] == "highest"
    )  # as the preset says
    assert [e["step"] for e in results["evaluations"]] == [100, 200]
    for key in ("normalized_feasible_return", "normalized_cost", "feasible_return"):
        assert math.isfinite(results["aggregate"][key]), key
    assert "| normalized_feasible_return |" in run.ran.stdout and "Traceback" not in run.ran.stderr
    assert not (run.dir / "run.lock").exists() and not (run.dir / "logs").exists()  # logger=none


@pytest.mark.parametrize("algo", ALGOS)
def test_a_run_saves_a_policy_for_its_task(smoke, algo):
    from spoil_torchrl.zoo import load_policy

    run = smoke(algo)
    _, meta = load_policy(run.dir / "checkpoints" / "policy.pt", env_id="SafetyPointCircle1-v0")
    assert meta["info"]["step"] == 200
    assert meta["observation_norm"] is ("normalize_observations=false" not in EXTRA.get(algo, []))


@pytest.mark.parametrize("algo", ALGOS)
def test_a_run_records_its_settings_and_data(smoke, algo):
    run = smoke(algo)
    config = (run.dir / "config.yaml").read_text()
    assert f"name: {algo}\n" in config and (run.dir / ".hydra" / "config.yaml").is_file()
    data = run.results["data"]
    assert data["safe"]["episodes"] == 2 and data["performant"]["episodes"] == 2
    assert len(data["fingerprint"]) == 16 and data["cost_threshold"] == 25.0


@pytest.mark.parametrize("algo", ALGOS)
def test_a_run_s_rollout_file_holds_its_evaluations_episodes(smoke, algo):
    from spoil_torchrl.eval import read_rollouts

    run = smoke(algo)
    rollouts = read_rollouts(run.dir / "rollouts.mcap")
    assert rollouts.finished and rollouts.metadata["algo"] == algo
    lengths = [length for e in run.results["evaluations"] for length in e["episodes"]["length"]]
    assert rollouts.episodes["length"].tolist() == lengths
    assert rollouts.episodes["evaluation_step"].tolist() == [100, 200]


def test_bc_has_no_pre_training_and_no_dice_diagnostics(smoke):
    results = smoke("bc").results
    assert results["diagnostics"] == {}
    assert "dice_diagnostics" not in results and "dice" not in results["evaluations"][0]


def test_spoildice_cuts_the_unlabeled_data_with_its_support(smoke):
    results = smoke("spoildice").results
    assert 0.0 < results["diagnostics"]["support_share_unlabeled"] <= 1.0
    assert 0.0 <= results["performant_support"]["kept"] <= 1.0
    assert all("dice/share_bellman" in e["dice"] for e in results["evaluations"])


def test_safedice_gets_its_nonpreferred_role(smoke):
    results = smoke("safedice").results
    nonpreferred = results["data"]["nonpreferred"]
    assert nonpreferred["safe_share"] == 0.0 and nonpreferred["episodes"] > 0
    assert 0.0 <= results["diagnostics"]["alpha"] < 1.0


def test_dwbc_s_takes_the_safe_demonstrations_as_its_expert(smoke):
    assert "unlabeled: safe" in (smoke("dwbc_s").dir / "config.yaml").read_text()


def test_coptidice_gets_the_episode_constraint(smoke):
    from spoil_torchrl.objectives import per_step_cost_limit

    results = smoke("coptidice").results
    threshold = results["data"]["cost_threshold"]
    assert results["diagnostics"]["cost_limit"] == per_step_cost_limit(threshold, 500, 0.99)
