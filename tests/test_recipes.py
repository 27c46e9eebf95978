"""The recipes run end to end (tiny settings), in this process (tests/cli.py)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from tests.cli import Ran, run_command

pytestmark = pytest.mark.runs

ROOT = Path(__file__).resolve().parents[1]


def test_tabular_recipe_end_to_end(tmp_path):
    cmd = [
        "recipes/tabular_spoildice.py",
        "seeds=[0,1]",
        "training.n_samples=3000",
        "training.n_init=200",
        "training.discriminator_steps=30",
        "training.dice_steps=30",
        "progress=false",
        f"hydra.run.dir={tmp_path}",
    ]
    proc = run_command(cmd, cwd=ROOT, real=True)  # spoil-tabular-check in a process of its own
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Tabular check" in proc.stdout
    assert "| SpoilDICE neural |" in proc.stdout
    results = json.loads((tmp_path / "results.json").read_text())
    assert [r["seed"] for r in results] == [0, 1]
    for result in results:
        assert 0.0 <= result["tv_neural_vs_exact"] <= 1.0
        assert result["policies"]["SpoilDICE exact"]["cost"] == 0.0
        assert result["policies"]["BC (d_P)"]["cost"] > 0.05  # the performant data are unsafe
        assert result["tv_bc_vs_exact"] > 0.2
    assert list(tmp_path.rglob("*.csv")), "the TorchRL CSV logger wrote nothing"
    assert (
        "\x1b" not in proc.stdout + proc.stderr
    )  # no ANSI colour codes (TorchRL's logger is routed plainly)
    assert "| SpoilDICE neural |" in (tmp_path / "tabular_spoildice.log").read_text()  # Hydra's run log


def test_train_experts_recipe_tiny(tmp_path):
    import importlib.util

    import pytest

    if importlib.util.find_spec("safety_gymnasium") is None:
        pytest.skip("safety-gymnasium not installed")
    cmd = [
        "recipes/train_experts.py",
        "env_id=SafetyPointCircle1-v0",  # the key must not clash with the main recipe's task/ config group
        "ppo.total_frames=500",
        "ppo.frames_per_batch=500",
        "ppo.minibatch_size=250",
        "ppo.epochs=1",
        "ppo.lagrangian=true",
        "progress=false",
        f"hydra.run.dir={tmp_path}",
    ]
    proc = run_command(cmd, cwd=ROOT, real=True)  # spoil-train-experts in a process of its own
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "SafetyPointCircle1-v0: 500 frames" in proc.stdout
    assert list(tmp_path.glob("ckpt_*.pt"))


def _dsrl_recipe(tmp_path, dataset, *overrides):
    cmd = [
        "recipes/spoildice_dsrl.py",
        "preset=smoke",
        f"dataset.source=file:{dataset}",
        "dataset.n_safe=2",
        "dataset.n_performant=2",
        "progress=false",
        f"hydra.run.dir={tmp_path}",
        *overrides,
    ]
    proc = run_command(cmd, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc, json.loads((tmp_path / "results.json").read_text())


def test_dsrl_recipe_smoke_end_to_end(tmp_path, tiny_pc1_dataset):
    from spoil_torchrl.eval import read_rollouts
    from spoil_torchrl.precision import REDUCED_PRECISION_ERROR, matmul_precision, matmul_relative_error
    from spoil_torchrl.stack import current_stack
    from spoil_torchrl.zoo import load_policy

    proc, results = _dsrl_recipe(
        tmp_path, tiny_pc1_dataset, "train.compile=true", "train.matmul_precision=medium"
    )
    assert results["update_step"] == "compiled" and "runs eagerly" not in proc.stdout + proc.stderr
    with matmul_precision("medium"):
        bfloat16 = matmul_relative_error() > REDUCED_PRECISION_ERROR  # a CPU with AMX: IEEE instead
    assert results["matmul_precision"] == ("highest" if bfloat16 else "medium")
    assert 0 < results["matmul_relative_error"] <= REDUCED_PRECISION_ERROR
    assert "| normalized_feasible_return |" in proc.stdout
    assert "| normalized_feasible_return |" in (tmp_path / "spoildice_dsrl.log").read_text()
    assert "\x1b" not in proc.stdout + proc.stderr and "AdroitHand" not in proc.stderr
    assert results["status"] == "finished" and results["algo"] == "spoildice"
    assert [e["step"] for e in results["evaluations"]] == [100, 200]
    assert results["data_seconds"] > 0 and all(e["eval_seconds"] > 0 for e in results["evaluations"])
    assert set(results["aggregate"]) >= {"normalized_feasible_return", "normalized_cost", "feasible_return"}
    assert 0.0 < results["diagnostics"]["support_share_unlabeled"] <= 1.0
    assert results["data"]["safe"]["episodes"] == 2
    assert results["stack"] == current_stack() and results["data"]["stack"] == current_stack()
    rollouts = read_rollouts(tmp_path / "rollouts.mcap")
    assert rollouts.episodes.shape[0] == 2 and rollouts.metadata["algo"] == "spoildice"
    _, meta = load_policy(tmp_path / "checkpoints" / "policy.pt", env_id="SafetyPointCircle1-v0")
    assert meta["distribution"] == "normal" and meta["info"]["step"] == 200
    assert meta["observation_norm"] is True  # standardised by default, the statistics inside the policy file
    assert "train:" in (tmp_path / "config.yaml").read_text()
    assert list((tmp_path / "logs").rglob("dice.loss_nu.csv"))
    # DICE diagnostics: at every evaluation (and logged), in full at the end, and as sentences
    assert all("dice/share_bellman" in e["dice"] for e in results["evaluations"])
    assert list((tmp_path / "logs").rglob("dice/weight_on_cost.csv"))
    diag = results["dice_diagnostics"]
    assert diag["role"] == "unlabeled" and sum(diag["variance_share"].values()) == pytest.approx(
        1.0, abs=1e-4
    )
    assert 0.0 <= diag["weight_share"]["cost>0"]["weight"] <= 1.0
    assert 0.0 <= results["performant_support"]["kept"] <= 1.0
    assert "of the weight mass sits on transitions with true cost > 0" in results["dice_report"]
    assert results["dice_report"] in proc.stdout


def _two_constraint_file(source, target):
    """``source``'s transitions with two constraints' costs: ``a`` is the task's cost, ``b`` the same on every
    second episode only (so the safe sets differ and their supports meet)."""
    import h5py
    import numpy as np

    from spoil_torchrl.data.hdf5 import read_metadata, write_dsrl_file

    with h5py.File(source) as f:
        arrays = {k: f[k][()] for k in f}
    ends = np.logical_or(arrays["terminals"], arrays["timeouts"]).astype(np.int64)
    episode = np.concatenate([[0], np.cumsum(ends[:-1])])
    arrays["cost_a"] = arrays["costs"]
    arrays["cost_b"] = arrays["costs"] * (episode % 2 == 1)
    return write_dsrl_file(target, arrays, metadata=read_metadata(source))


def test_spoildice_and_fbc_with_two_constraints_end_to_end_and_other_methods_refuse_them(
    tmp_path, tiny_pc1_dataset
):
    dataset = _two_constraint_file(tiny_pc1_dataset, tmp_path / "two.hdf5")
    run_dir = tmp_path / "run"
    proc, results = _dsrl_recipe(run_dir, dataset, "+dataset.constraints=[a,b]")
    assert results["status"] == "finished" and results["data"]["safe_a"]["episodes"] == 2
    diagnostics = results["diagnostics"]
    assert {"support_threshold_a", "support_threshold_b", "support_share_unlabeled_b"} <= set(diagnostics)
    assert diagnostics["support_share_unlabeled"] <= min(
        diagnostics["support_share_unlabeled_a"], diagnostics["support_share_unlabeled_b"]
    )  # the intersection
    for where in (results["dice_diagnostics"]["support"], results["performant_support"]):
        by = where["by_constraint"]  # each cut against each constraint's own cost, and their intersection
        assert set(by["costly_kept"]) == {"a", "b", "all"} and set(by["costly"]) == {"a", "b"}
        assert all(
            by["costly_kept"]["all"][j] <= min(by["costly_kept"]["a"][j], by["costly_kept"]["b"][j])
            for j in ("a", "b")
        )
    logged = (run_dir / "logs").rglob("*lagrange_1*")
    assert any(logged), "no per-constraint multiplier was logged"
    proc = run_command(
        [
            "recipes/spoildice_dsrl.py",
            "preset=smoke",
            "algo=bc",
            f"dataset.source=file:{dataset}",
            "+dataset.constraints=[a,b]",
            f"hydra.run.dir={tmp_path / 'bc'}",
        ],
        cwd=ROOT,
    )
    assert proc.returncode == 2 and "taken by algo=spoildice | fbc only" in proc.stderr
    proc, results = _dsrl_recipe(tmp_path / "fbc", dataset, "+dataset.constraints=[a,b]", "algo=fbc")
    diagnostics = results["diagnostics"]
    assert results["status"] == "finished" and {"support_threshold_a", "support_threshold_b"} <= set(
        diagnostics
    )
    assert diagnostics["support_share_performant"] <= min(  # FBC's filter: D_P inside both supports
        diagnostics["support_share_performant_a"], diagnostics["support_share_performant_b"]
    )


@pytest.mark.parametrize(
    "override, message",
    [
        (
            "+eval.constraints=x_wall",
            "eval.constraints = 'x_wall': expected a list of distinct constraint names",
        ),
        (
            "+eval.constraints=[x_wall]",
            "SafetyPointCircle1-v0 reports the per-constraint costs of no constraint",
        ),
    ],
)
def test_constraints_to_evaluate_are_checked_before_training(tmp_path, tiny_pc1_dataset, override, message):
    cmd = [
        "recipes/spoildice_dsrl.py",
        "preset=smoke",
        f"dataset.source=file:{tiny_pc1_dataset}",
        "dataset.n_safe=2",
    ]
    cmd += ["dataset.n_performant=2", override]
    proc = run_command([*cmd, f"hydra.run.dir={tmp_path}"], cwd=ROOT)
    assert proc.returncode == 2 and message in proc.stderr, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and not list(tmp_path.rglob("*.ckpt"))


def test_dsrl_recipe_rejects_bad_settings_before_training(tmp_path, tiny_pc1_dataset):
    cmd = [
        "recipes/spoildice_dsrl.py",
        "preset=smoke",
        f"dataset.source=file:{tiny_pc1_dataset}",
        "train.eval_interval=0",
        f"hydra.run.dir={tmp_path}",
    ]
    proc = run_command(cmd, cwd=ROOT)
    assert proc.returncode == 2 and "train.eval_interval = 0: expected an integer >= 1" in proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "results.json").exists()


def test_collect_demos_recipe_reuses_a_cached_dataset(tmp_path, monkeypatch):
    import importlib.util

    import pytest

    if importlib.util.find_spec("safety_gymnasium") is None:
        pytest.skip("safety-gymnasium not installed")
    from spoil_torchrl.data import Segment, collect
    from spoil_torchrl.data.generated import get_generated

    # a cached file with the right fingerprint is reused: no rollout, just the Table-I-style summary
    spec = get_generated("point-circle1-controlled")
    collect(
        spec.env_id,
        [Segment("safe-high", "zoo:safe-high", 1)],
        tmp_path / "point-circle1-controlled.hdf5",
        num_envs=1,
        reference_episodes=1,
        progress=False,
        metadata={"fingerprint": spec.fingerprint(8), "name": spec.name},
    )
    cmd = [
        "recipes/collect_demos.py",
        "name=point-circle1-controlled",
        "progress=false",
        f"hydra.run.dir={tmp_path / 'run'}",
    ]
    env = {**__import__("os").environ, "SPOIL_TORCHRL_DATA_DIR": str(tmp_path)}
    proc = run_command(cmd, cwd=ROOT, env=env, real=True)  # spoil-collect in a process of its own
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "| safe-high | 1 |" in proc.stdout


def test_score_checkpoints_scores_zoo_policies(tmp_path):
    zoo = ROOT / "spoil_torchrl" / "zoo" / "SafetyPointCircle1-v0"
    cmd = [
        "recipes/score_checkpoints.py",
        str(zoo / "safe-high.pt"),
        str(zoo / "unsafe-high.pt"),
        "--episodes",
        "2",
    ]
    proc = run_command(cmd, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = {line.split("|")[1].strip(): line for line in proc.stdout.splitlines() if line.startswith("| ")}
    assert set(rows) == {"checkpoint", "safe-high.pt", "unsafe-high.pt"}
    # unsafe-high circles outside the boundary: every episode is over the limit; safe-high stays near it
    assert rows["unsafe-high.pt"].rstrip().endswith("| 100 % |")
    unsafe_cost = float(rows["unsafe-high.pt"].split("|")[5].split("±")[0])
    safe_cost = float(rows["safe-high.pt"].split("|")[5].split("±")[0])
    assert safe_cost < 25.0 < unsafe_cost


def test_score_checkpoints_reports_each_constraints_cost_with_components(tmp_path):
    zoo = ROOT / "spoil_torchrl" / "zoo" / "SafetyPointCircle2-v0"
    cmd = ["recipes/score_checkpoints.py", str(zoo / "unsafe-high.pt"), str(zoo / "safe-high.pt")]
    proc = run_command(
        [*cmd, "--env-id", "SafetyPointCircle2-v0", "--episodes", "2", "--components"], cwd=ROOT
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = [line for line in proc.stdout.splitlines() if line.startswith("| ")]
    assert lines[0].endswith("| x_wall | y_wall |") and len(lines) == 3  # one header, two rows
    unsafe = lines[1].split("|")
    assert (
        float(unsafe[7].split("(")[0]) > 25.0 and float(unsafe[8].split("(")[0]) > 25.0
    )  # both walls crossed
    assert "(0 % within)" in unsafe[7]
    pc1 = str(ROOT / "spoil_torchrl" / "zoo" / "SafetyPointCircle1-v0" / "safe-high.pt")
    proc = run_command([cmd[0], pc1, "--components"], cwd=ROOT)  # PointCircle1 computes no constraint's cost
    assert proc.returncode == 2 and "SafetyPointCircle1-v0 has no per-constraint costs" in proc.stderr


def test_score_checkpoints_rejects_a_missing_path(tmp_path):
    cmd = ["recipes/score_checkpoints.py", str(tmp_path / "nope")]
    proc = run_command(cmd, cwd=ROOT, real=True)  # spoil-score-checkpoints in a process of its own
    assert proc.returncode != 0
    assert "no such file or folder" in proc.stderr


def test_dataset_configs_select_their_evaluation_task():
    from hydra import compose, initialize_config_dir

    from spoil_torchrl.data import get_generated

    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        for dataset, env_id in [
            ("point_circle1_mixed", "SafetyPointCircle1-v0"),
            ("point_circle1_controlled", "SafetyPointCircle1-v0"),
            ("half_cheetah_velocity_controlled", "SafetyHalfCheetahVelocity-v1"),
            ("hopper_velocity_controlled", "SafetyHopperVelocity-v1"),
            ("walker2d_velocity_controlled", "SafetyWalker2dVelocity-v1"),
            ("ant_velocity_controlled", "SafetyAntVelocity-v1"),
        ]:
            cfg = compose(config_name="spoildice_dsrl", overrides=[f"dataset={dataset}"])
            assert cfg.task.env_id == env_id, dataset
            name = cfg.dataset.source.removeprefix("generated:")
            assert get_generated(name).env_id == env_id, dataset


def _recipe(name: str, *overrides: str, env=None, real=False) -> Ran:
    """Run ``recipes/<name>.py`` with ``overrides`` (quietly); fails the test on a non-zero exit."""
    cmd = [f"recipes/{name}.py", "progress=false", *overrides]
    proc = run_command(cmd, cwd=ROOT, env=env, real=real)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def test_minari_export_and_training_on_it(tmp_path, tiny_pc1_dataset):
    pytest.importorskip("minari")
    env = {**os.environ, "MINARI_DATASETS_PATH": str(tmp_path / "minari")}
    proc = _recipe(
        "export_minari",
        f"dataset.source=file:{tiny_pc1_dataset}",
        "dataset.n_safe=2",
        "dataset.n_performant=2",
        "dataset_id=test/tiny-pc1-v0",
        f"hydra.run.dir={tmp_path / 'export'}",
        env=env,
        real=True,  # spoil-export-minari in a process of its own
    )
    assert "test/tiny-pc1-v0: 12 episodes" in proc.stdout and "AdroitHand" not in proc.stderr
    _recipe(
        "spoildice_dsrl",
        "preset=smoke",
        "train.batch_size=64",
        "dataset.source=minari:test/tiny-pc1-v0",
        "dataset.scheme=stored",
        "logger=none",
        f"hydra.run.dir={tmp_path / 'train'}",
        env=env,
    )
    results = json.loads((tmp_path / "train" / "results.json").read_text())
    assert results["status"] == "finished" and results["data"]["safe"]["episodes"] == 2
    assert results["data"]["unlabeled"]["episodes"] == 12


def test_a_run_of_an_overridden_source_is_named_after_it():
    from omegaconf import OmegaConf

    from spoil_torchrl.runs.settings import name_dataset_by_source

    cfg = OmegaConf.create({"dataset": {"name": "point-circle1-mixed", "source": "file:/d/mine.hdf5"}})
    name_dataset_by_source(cfg, ["dataset.source=file:/d/mine.hdf5", "seed=1"])
    assert cfg.dataset.name == "mine"
    cfg = OmegaConf.create({"dataset": {"name": "given", "source": "file:/d/mine.hdf5"}})
    name_dataset_by_source(cfg, ["dataset.source=file:/d/mine.hdf5", "dataset.name=given"])
    assert cfg.dataset.name == "given"
