"""PPO / PPO-Lagrangian training loop: a tiny run end to end, checkpoints and the Lagrange update."""

from __future__ import annotations

import functools
import importlib.util
import json

import pytest
import torch

from spoil_torchrl.experts.ppo import EpisodeTracker, PPOConfig, train_ppo


def test_episode_tracker_spans_batches():
    from tensordict import TensorDict

    def batch(rewards, costs, dones):
        n = len(rewards)
        return TensorDict(
            {
                "next": {
                    "reward": torch.tensor(rewards).view(n, 1),
                    "cost": torch.tensor(costs).view(n, 1),
                    "done": torch.tensor(dones).view(n, 1),
                }
            },
            [n],
        )

    tracker = EpisodeTracker()
    assert tracker.update(batch([1.0, 1.0], [0.0, 1.0], [False, False]))[2] == 0
    ret, cost, n = tracker.update(batch([1.0, 2.0, 5.0], [1.0, 0.0, 3.0], [True, False, True]))
    # episode 1: rewards 1+1+1, costs 0+1+1; episode 2: rewards 2+5, costs 0+3
    assert (ret, cost, n) == (5.0, 2.5, 2)


@pytest.mark.skipif(
    importlib.util.find_spec("safety_gymnasium") is None, reason="safety-gymnasium not installed"
)
@pytest.mark.parametrize("lagrangian", [False, True])
def test_tiny_ppo_run_writes_checkpoints(tmp_path, lagrangian):
    from spoil_torchrl.envs import make_env
    from spoil_torchrl.modules import make_actor

    config = PPOConfig(
        total_frames=1000,
        frames_per_batch=500,
        epochs=1,
        minibatch_size=250,
        lagrangian=lagrangian,
        checkpoint_every=1,
        cost_limit=0.0,
    )
    log = train_ppo(
        functools.partial(make_env, "SafetyPointCircle1-v0", seed=0), 28, 2, config, tmp_path, progress=False
    )
    assert [line["frames"] for line in log] == [500, 1000]
    checkpoints = sorted(tmp_path.glob("ckpt_*.pt"))
    assert len(checkpoints) == 2
    state = torch.load(checkpoints[-1], weights_only=True)
    actor = make_actor(28, 2, hidden_cells=config.hidden_cells)
    actor.load_state_dict(state["actor"])
    assert json.loads((tmp_path / "config.json").read_text())["lagrangian"] == lagrangian
    lines = (tmp_path / "log.jsonl").read_text().splitlines()
    assert len(lines) == 2
    if lagrangian:  # cost limit 0 and a random policy that leaves the band: lambda must have grown
        assert log[-1]["lagrange"] > 0
    else:
        assert log[-1]["lagrange"] == 0


# --- committed policies ------------------------------------------------------------------------------------


@pytest.mark.parametrize("env_id", ["SafetyPointCircle1-v0", "SafetyHalfCheetahVelocity-v1"])
def test_zoo_has_the_four_policy_types(env_id):
    from spoil_torchrl.experts import load_policy, zoo_names, zoo_policy

    names = zoo_names(env_id)
    assert {"safe-high", "safe-medium", "unsafe-high", "unsafe-medium"} <= set(names)
    for name in names:
        raw = torch.load(zoo_policy(env_id, name), weights_only=True)
        assert raw["env_id"] == env_id and raw["hidden_cells"] == [64, 64]
        _, meta = load_policy(zoo_policy(env_id, name), env_id=env_id)
        expected = "PPO-Lagrangian" if name.startswith(("safe", "ppolag")) else "PPO"
        assert meta["info"]["algorithm"] == expected, name


def test_zoo_policies_load_with_weights_only_and_check_the_task():
    from spoil_torchrl.experts import PolicyFileError, load_policy, zoo_policy

    actor, meta = load_policy(
        zoo_policy("SafetyPointCircle1-v0", "safe-high"), env_id="SafetyPointCircle1-v0"
    )
    assert meta["info"]["algorithm"] == "PPO-Lagrangian" and not actor.training
    with pytest.raises(PolicyFileError, match="not SafetyHalfCheetahVelocity-v1"):
        load_policy(zoo_policy("SafetyPointCircle1-v0", "safe-high"), env_id="SafetyHalfCheetahVelocity-v1")
    with pytest.raises(PolicyFileError, match="no committed policy"):
        zoo_policy("SafetyPointCircle1-v0", "best-ever")


def test_load_policy_reads_raw_training_checkpoints_and_rejects_junk(tmp_path):
    from spoil_torchrl.experts import PolicyFileError, export_checkpoint, load_policy
    from spoil_torchrl.experts import policies as policies_module
    from spoil_torchrl.modules import make_actor

    actor = make_actor(17, 6, hidden_cells=(16, 8))
    torch.save({"actor": actor.state_dict(), "frames": 10, "episode_return": 1.5}, tmp_path / "ckpt.pt")
    loaded, meta = load_policy(tmp_path / "ckpt.pt", env_id="SafetyHalfCheetahVelocity-v1")
    assert meta["hidden_cells"] == [16, 8] and meta["env_id"] is None and meta["info"]["frames"] == 10
    for a, b in zip(actor.parameters(), loaded.parameters(), strict=True):
        assert torch.equal(a, b)
    with pytest.raises(PolicyFileError, match="sizes 17/6"):
        load_policy(tmp_path / "ckpt.pt", env_id="SafetyPointCircle1-v0")
    (tmp_path / "junk.pt").write_text("not a checkpoint")
    with pytest.raises(PolicyFileError, match="not a policy checkpoint"):
        load_policy(tmp_path / "junk.pt")
    with pytest.raises(PolicyFileError, match="no such policy file"):
        load_policy(tmp_path / "missing.pt")
    policies_module_zoo = policies_module.ZOO_DIR
    try:
        policies_module.ZOO_DIR = tmp_path / "zoo"
        path = export_checkpoint(tmp_path / "ckpt.pt", "SafetyHalfCheetahVelocity-v1", "mine", info={"x": 1})
        _, meta = load_policy(path, env_id="SafetyHalfCheetahVelocity-v1")
        assert meta["env_id"] == "SafetyHalfCheetahVelocity-v1"
        assert meta["info"]["x"] == 1 and meta["info"]["exported_from"] == "ckpt.pt"
    finally:
        policies_module.ZOO_DIR = policies_module_zoo
