"""The committed policies (spoil_torchrl/zoo): the four policy types of each task, loaded with
``weights_only`` and checked against their task, and the policy file format's refusals."""

from __future__ import annotations

import pytest
import torch


@pytest.mark.parametrize(
    "env_id",
    [
        "SafetyPointCircle1-v0",
        "SafetyPointCircle2-v0",
        "SafetyHalfCheetahVelocity-v1",
        "SafetyHopperVelocity-v1",
        "SafetyWalker2dVelocity-v1",
        "SafetyAntVelocity-v1",
    ],
)
def test_zoo_has_the_four_policy_types(env_id):
    """Each policy says how it was trained: a safe one by PPO-Lagrangian or by PPO on a cost-penalised reward
    (docs/experts.md says which, per task), one safe on a single constraint by PPO-Lagrangian against that
    constraint's cost, an unsafe one by PPO."""
    from spoil_torchrl.zoo import load_policy, zoo_names, zoo_policy

    names = zoo_names(env_id)
    assert {"safe-high", "safe-medium", "unsafe-high", "unsafe-medium"} <= set(names)
    for name in names:
        raw = torch.load(zoo_policy(env_id, name), weights_only=True)
        assert raw["env_id"] == env_id and raw["hidden_cells"] == [64, 64]
        _, meta = load_policy(zoo_policy(env_id, name), env_id=env_id)
        trainer = meta["info"].get("algorithm", meta["info"].get("trainer"))
        if name.endswith("-wall-safe"):  # safe on one constraint: trained against that constraint's cost only
            assert (
                trainer.startswith("PPO-Lagrangian against the")
                and meta["info"]["training"]["cost_component"]
            )
        elif name.startswith(("safe", "ppolag")):
            assert trainer == "PPO-Lagrangian" or trainer.startswith("PPO with cost penalty"), name
        else:
            assert trainer == "PPO" or trainer.startswith("PPO, "), name


def test_zoo_policies_load_with_weights_only_and_check_the_task():
    from spoil_torchrl.zoo import PolicyFileError, load_policy, zoo_policy

    actor, meta = load_policy(
        zoo_policy("SafetyPointCircle1-v0", "safe-high"), env_id="SafetyPointCircle1-v0"
    )
    assert meta["info"]["algorithm"] == "PPO-Lagrangian" and not actor.training
    with pytest.raises(PolicyFileError, match="not SafetyHalfCheetahVelocity-v1"):
        load_policy(zoo_policy("SafetyPointCircle1-v0", "safe-high"), env_id="SafetyHalfCheetahVelocity-v1")
    with pytest.raises(PolicyFileError, match="no committed policy"):
        zoo_policy("SafetyPointCircle1-v0", "best-ever")


def test_load_policy_reads_raw_training_checkpoints_and_rejects_junk(tmp_path):
    from spoil_torchrl.modules import make_actor
    from spoil_torchrl.zoo import PolicyFileError, export_checkpoint, load_policy
    from spoil_torchrl.zoo import policy_files as policies_module

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


# --- the recipe, killed for real ---------------------------------------------------------------------------
