"""The evaluator in the real environment: deterministic episodes, metrics, MCAP output."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from spoil_torchrl.eval import Evaluator, RolloutWriter, pad_episodes, read_rollouts


def test_pad_episodes_masks_and_rejects_unfinished():
    arrays = {
        "observations": np.arange(5, dtype=np.float32).reshape(5, 1),
        "actions": np.zeros((5, 1), np.float32),
        "rewards": np.array([1.0, 2.0, 3.0, 4.0, 5.0]),
        "costs": np.array([0.0, 1.0, 0.0, 0.0, 1.0]),
        "terminals": np.array([False, True, False, False, False]),
        "timeouts": np.array([False, False, False, False, True]),
    }
    td = pad_episodes(arrays)
    assert td.batch_size == (2, 3)
    assert td["next", "reward"].tolist() == [[1.0, 2.0, 0.0], [3.0, 4.0, 5.0]]
    assert td["next", "terminated"][0, 1] and td["next", "truncated"][1, 2]
    arrays["timeouts"] = np.zeros(5, bool)
    with pytest.raises(ValueError, match="finished episode"):
        pad_episodes(arrays)


@pytest.mark.skipif(importlib.util.find_spec("safety_gymnasium") is None, reason="safety-gymnasium missing")
def test_evaluator_metrics_and_mcap(tmp_path):
    from spoil_torchrl.zoo import load_policy, zoo_policy

    policy, _ = load_policy(zoo_policy("SafetyPointCircle1-v0", "unsafe-high"))
    with RolloutWriter(tmp_path / "r.mcap", cost_threshold=25.0) as writer:
        evaluator = Evaluator(
            "SafetyPointCircle1-v0", cost_threshold=25.0, return_range=(0.0, 40.0), episodes=2, writer=writer
        )
        first = evaluator(policy, step=10)
        second = evaluator(policy, step=20)
    # deterministic actions and the same seed: the same episodes
    assert first["return"] == second["return"] and first["cost"] == second["cost"]
    assert first["cost"] > 25.0 and first["feasible_return"] < first["return"]  # the unconstrained expert
    assert first["normalized_cost"] == pytest.approx(first["cost"] / 25.0)
    assert first["normalized_return"] == pytest.approx(first["return"] / 40.0)
    assert first["episodes"]["length"] == [500, 500]
    rollouts = read_rollouts(tmp_path / "r.mcap")
    assert rollouts.episodes.shape[0] == 4
    assert rollouts.episodes["return"][:2].tolist() == pytest.approx(first["episodes"]["return"])
    with pytest.raises(ValueError, match="return_range"):
        Evaluator("SafetyPointCircle1-v0", cost_threshold=25.0, return_range=(1.0, 1.0))


@pytest.mark.skipif(importlib.util.find_spec("safety_gymnasium") is None, reason="safety-gymnasium missing")
def test_an_evaluation_does_not_depend_on_the_callers_matmul_precision():
    """``train.matmul_precision`` is training's: a policy's evaluation is the same whatever level it is called at
    (on this project's CPUs ``medium`` moves this policy's actions in the last bits, which the simulator amplifies
    into other episodes)."""
    import torch

    from spoil_torchrl.modules import make_actor
    from spoil_torchrl.precision import matmul_precision

    torch.manual_seed(0)
    policy = make_actor(28, 2, hidden_cells=(256, 256))
    evaluator = Evaluator("SafetyPointCircle1-v0", cost_threshold=25.0, return_range=(0.0, 40.0), episodes=2)
    ieee = evaluator(policy)
    with matmul_precision("medium"):
        medium = evaluator(policy)
        assert torch.get_float32_matmul_precision() == "medium"  # the caller's level, restored
    assert medium["episodes"] == ieee["episodes"]


@pytest.mark.skipif(importlib.util.find_spec("safety_gymnasium") is None, reason="safety-gymnasium missing")
def test_an_evaluation_does_not_depend_on_the_callers_threads():
    """A ``seeds=[...]`` run trains at ``threads=2`` and evaluates some seeds in 1-thread worker processes: the
    rollout runs its policy at one thread, so an evaluation is the same whatever the caller's threads (ten
    environments of a [256, 256] policy: the batch whose products differ in the last bits between one and two
    threads on this project's CPUs)."""
    import torch

    from spoil_torchrl.modules import make_actor
    from spoil_torchrl.precision import intra_op_threads

    torch.manual_seed(0)
    policy = make_actor(28, 2, hidden_cells=(256, 256))
    evaluator = Evaluator(
        "SafetyPointCircle1-v0", cost_threshold=25.0, return_range=(0.0, 40.0), episodes=10, num_envs=10
    )
    with intra_op_threads(1):
        one = evaluator(policy)
    with intra_op_threads(2):
        two = evaluator(policy)
        assert torch.get_num_threads() == 2  # the caller's, restored
    assert two["episodes"] == one["episodes"]


@pytest.mark.skipif(importlib.util.find_spec("safety_gymnasium") is None, reason="needs safety-gymnasium")
def test_an_evaluation_with_several_constraints_reports_each_and_their_joint_feasibility():
    from spoil_torchrl.zoo import load_policy, zoo_policy

    policy, _ = load_policy(zoo_policy("SafetyPointCircle2-v0", "unsafe-high"))
    limits = {"x_wall": 25.0, "y_wall": 60.0}
    evaluator = Evaluator(
        "SafetyPointCircle2-v0",
        cost_threshold=25.0,
        return_range=(0.0, 1.0),
        episodes=3,
        num_envs=3,
        constraints=limits,
    )
    result = evaluator(policy, step=1)
    episodes = result["episodes"]
    within = [
        float(x <= limits["x_wall"] and y <= limits["y_wall"])
        for x, y in zip(episodes["cost_x_wall"], episodes["cost_y_wall"], strict=True)
    ]
    assert episodes["feasible_all"] == within and result["feasible_all"] == pytest.approx(np.mean(within))
    assert result["cost_x_wall"] > 0 and result["cost_y_wall"] > 0
    # the task's cost is the union of the walls': never more than their sum, never less than either
    costs = np.array(episodes["cost"])
    assert np.all(costs <= np.add(episodes["cost_x_wall"], episodes["cost_y_wall"]) + 1e-9)
    assert np.all(costs >= np.maximum(episodes["cost_x_wall"], episodes["cost_y_wall"]) - 1e-9)
    with pytest.raises(ValueError, match="SafetyPointCircle1-v0 has no per-constraint costs"):
        Evaluator("SafetyPointCircle1-v0", cost_threshold=25.0, return_range=(0.0, 1.0), constraints=limits)
