"""The offline Trainer glue: batch source, several losses and optimisers in one step, hooks, the builders."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from spoil_torchrl.modules import make_actor, make_value_network
from spoil_torchrl.objectives import SpoilDICELoss, WeightedBCLoss
from spoil_torchrl.trainers import MultiLossStepper, OfflineBatchSource, offline_trainer
from tests.conftest import ACT_DIM, OBS_DIM, dual_batch


def test_batch_source_counts_steps_and_validates():
    source = OfflineBatchSource(total_steps=250, steps_per_batch=100)
    assert [c.batch_size[0] for c in source] == [100, 100, 50]
    assert source.state_dict() == {"steps": 250}
    with pytest.raises(ValueError, match="total_steps"):
        OfflineBatchSource(0, 10)


def _spoildice_stepper():
    dice = SpoilDICELoss(make_value_network(OBS_DIM, hidden_cells=(16,)), gradient_penalty=1.0)
    actor = WeightedBCLoss(
        make_actor(OBS_DIM, ACT_DIM, hidden_cells=(16,)), role="unlabeled", weight="dice_weight"
    )
    optims = [
        torch.optim.Adam(dice.nu_network_params.values(True, True), lr=1e-2),
        torch.optim.Adam([dice.lagrange], lr=1e-2),
        torch.optim.Adam(actor.parameters(), lr=1e-2),
    ]
    return MultiLossStepper({"dice": dice, "actor": actor}, optims), dice, actor


def test_stepper_updates_every_loss_and_chains_outputs():
    stepper, dice, actor = _spoildice_stepper()
    named = dict((*dice.named_parameters(), *actor.named_parameters()))
    before = {name: p.detach().clone() for name, p in named.items()}
    batch = dual_batch()
    assert not batch["unlabeled", "next", "terminated"].any()
    out = stepper.step(None, batch)
    # nu's output bias is the dual's free constant offset: without terminal transitions its gradient,
    # (1 - gamma) - 1 + gamma E_w[1 - d] = 0, vanishes and Adam leaves it; every other parameter moves
    offset = "nu_network_params.module.2.bias"
    assert named[offset].grad.abs().max() < 1e-6
    assert all(not torch.equal(before[name], p) for name, p in named.items() if name != offset)
    # the actor loss read the weights the dice loss wrote into the same batch
    assert "dice_weight" in batch["unlabeled"].keys()
    assert {"dice.loss_nu", "dice.loss_lambda", "actor.loss_actor"} <= set(out.keys())
    assert float(out["actor.weight_mean"]) == pytest.approx(
        float(batch["unlabeled", "dice_weight"].mean()), rel=1e-5
    )
    assert all(v.ndim == 0 and not v.requires_grad for v in out.values())


def test_stepper_state_dict_round_trip():
    stepper, dice, _ = _spoildice_stepper()
    stepper.step(None, dual_batch())
    state = stepper.state_dict()
    other, other_dice, _ = _spoildice_stepper()
    other.load_state_dict(state)
    assert torch.equal(other_dice.lagrange, dice.lagrange)
    assert (
        other.optimizers[0].state_dict()["state"].keys() == stepper.optimizers[0].state_dict()["state"].keys()
    )


def test_offline_trainer_runs_the_steps_and_the_hooks():
    stepper, dice, _ = _spoildice_stepper()
    samples, calls = [], []

    def sample():
        samples.append(1)
        return dual_batch()

    def hook(batch):
        calls.append(trainer.collected_frames)

    trainer = offline_trainer(stepper, sample, total_steps=25, steps_per_batch=10, progress_bar=False)
    trainer.register_op("post_steps_log", hook)
    trainer.train()
    # a short last chunk runs only its own steps: exactly total_steps samples and updates
    assert len(samples) == 25 and calls == [10, 20, 25]
    # the Trainer can checkpoint the losses it trains (its loss_module is a ModuleDict of them)
    losses_state = trainer.state_dict()["loss_module"]
    assert torch.equal(losses_state["dice.lagrange"], dice.lagrange.detach())
    assert any(key.startswith("actor.") for key in losses_state)
    with pytest.raises(ValueError, match="at least one"):
        MultiLossStepper({}, [])


def test_builders_train_spoildice_and_bc(tiny_pc1_dataset):
    from spoil_torchrl.algorithms import ALGORITHMS, BuildContext
    from spoil_torchrl.data import DualDemoBuffers, load_episodes

    episodes = load_episodes(f"file:{tiny_pc1_dataset}")
    roles = {"safe": torch.tensor([0, 1]), "performant": torch.tensor([6, 7]), "unlabeled": torch.arange(12)}
    buffers = DualDemoBuffers(episodes, roles, batch_size=64, seed=0)
    cfg = {
        "distribution": "normal",
        "hidden_cells": [16],
        "gamma": 0.99,
        "kappa": 0.01,
        "nu_gradient_penalty": 10.0,
        "init_lagrange": 0.0,
        "nu_lr": 1e-3,
        "lagrange_lr": 1e-3,
        "actor_lr": 1e-3,
        "discriminator": {
            "hidden_cells": [16],
            "gradient_penalty": {"performant": 10.0, "safe": 0.0},
            "lr": 1e-3,
            "steps": 5,
        },
    }
    training = ALGORITHMS["spoildice"](cfg, BuildContext(buffers, 28, 2, progress=False))
    unlabeled = buffers["unlabeled"].storage[:]
    assert {"log_ratio_performant", "safe_support"} <= set(unlabeled.keys())
    assert 0.0 < training.diagnostics["support_share_unlabeled"] <= 1.0
    out = training.stepper.step(None, buffers.sample())
    assert torch.isfinite(out["dice.loss_nu"]) and torch.isfinite(out["actor.loss_actor"])
    with training.policy() as policy:
        td = policy(TensorDict({"observation": torch.zeros(3, 28)}, [3]))
    assert td["action"].shape == (3, 2)
    bc = ALGORITHMS["bc"](
        {"distribution": "normal", "hidden_cells": [16], "actor_lr": 1e-3}, BuildContext(buffers, 28, 2)
    )
    assert set(bc.stepper.step(None, buffers.sample()).keys()) >= {"actor.loss_actor"}


def test_filtered_bc_builders_weight_by_the_estimated_supports(tiny_pc1_dataset):
    from spoil_torchrl.algorithms import ALGORITHMS, BuildContext
    from spoil_torchrl.data import DualDemoBuffers, load_episodes

    episodes = load_episodes(f"file:{tiny_pc1_dataset}")
    # safe: the safe-high episodes 0-2; performant: safe-high 2 and unsafe-high 6-7 (ids by policy type)
    roles = {
        "safe": torch.tensor([0, 1, 2]),
        "performant": torch.tensor([2, 6, 7]),
        "unlabeled": torch.arange(12),
    }
    buffers = DualDemoBuffers(episodes, roles, batch_size=64, seed=0)
    disc = {
        "hidden_cells": [16],
        "lr": 1e-3,
        "steps": 5,
        "gradient_penalty": {"performant": 0.0, "safe": 0.0},
    }
    common = {"distribution": "normal", "hidden_cells": [16], "kappa": 0.01, "actor_lr": 1e-3}
    fbc = ALGORITHMS["fbc"]({**common, "discriminator": disc}, BuildContext(buffers, 28, 2, progress=False))
    support = buffers["performant"].storage[:]["safe_support"]
    assert set(support.unique().tolist()) <= {0.0, 1.0}
    assert fbc.diagnostics["support_share_performant"] == pytest.approx(float(support.float().mean()))
    assert fbc.policy_loss.tensor_keys.weight == "safe_support"
    jfbc = ALGORITHMS["jfbc"]({**common, "discriminator": disc}, BuildContext(buffers, 28, 2, progress=False))
    unlabeled = buffers["unlabeled"].storage[:]
    assert torch.equal(unlabeled["jfbc_weight"], unlabeled["safe_support"] * unlabeled["performant_support"])
    out = jfbc.stepper.step(None, buffers.sample())
    assert torch.isfinite(out["actor.loss_actor"])


def _dice_baseline_cfg(penalties: dict) -> dict:
    return {
        "distribution": "normal",
        "hidden_cells": [16],
        "gamma": 0.99,
        "alpha": 0.1,
        "nu_gradient_penalty": 10.0,
        "nu_lr": 1e-3,
        "actor_lr": 1e-3,
        "discriminator": {"hidden_cells": [16], "gradient_penalty": penalties, "lr": 1e-3, "steps": 5},
    }


def test_builders_train_demodice_s_and_u(tiny_pc1_dataset):
    from spoil_torchrl.algorithms import ALGORITHMS, BuildContext, train_discriminators
    from spoil_torchrl.data import DualDemoBuffers, load_episodes

    episodes = load_episodes(f"file:{tiny_pc1_dataset}")
    roles = {"safe": torch.tensor([0, 1]), "performant": torch.tensor([6, 7]), "unlabeled": torch.arange(12)}
    buffers = DualDemoBuffers(episodes, roles, batch_size=64, seed=0)
    cfg = _dice_baseline_cfg({"performant": 10.0})

    demo_s = ALGORITHMS["demodice_s"](cfg, BuildContext(buffers, 28, 2, progress=False))
    assert "log_ratio_performant_safe" in buffers["safe"].storage[:].keys()
    assert "log_ratio_performant_safe" not in buffers["unlabeled"].storage[:].keys()
    dice = demo_s.stepper.losses["dice"]
    assert (
        dice.tensor_keys.regularization == "safe" and dice.tensor_keys.reward == "log_ratio_performant_safe"
    )
    assert dice.alpha == pytest.approx(0.1)
    assert demo_s.policy_loss.tensor_keys.role == "safe"
    assert set(demo_s.diagnostics) == {"log_ratio_performant_safe_mean", "log_ratio_performant_safe_std"}
    batch = buffers.sample()
    out = demo_s.stepper.step(None, batch)
    assert torch.isfinite(out["dice.loss_nu"]) and torch.isfinite(out["actor.loss_actor"])
    assert float(out["actor.weight_mean"]) == pytest.approx(1.0, rel=1e-5)
    assert "dice_weight" in batch["safe"].keys()

    # DemoDICE-S's discriminator is trained against D_S (not D_U): its logit is log d_P / d_S
    discs = train_discriminators(
        cfg["discriminator"] | {"steps": 1},
        BuildContext(buffers, 28, 2, progress=False),
        positives=("performant",),
        against="safe",
    )
    assert discs["performant"].tensor_keys.unlabeled == "safe"

    with pytest.raises(ValueError, match="no coefficient for \\['safe'\\]"):
        ALGORITHMS["demodice_u"](
            cfg, BuildContext(buffers, 28, 2, progress=False)
        )  # DemoDICE-U also trains C_S
    cfg_u = _dice_baseline_cfg({"performant": 10.0, "safe": 0.0})
    demo_u = ALGORITHMS["demodice_u"](cfg_u, BuildContext(buffers, 28, 2, progress=False))
    unlabeled = buffers["unlabeled"].storage[:]
    # DemoDICE-U regularises toward d_S like DemoDICE-S, sampling D_U: reward log r_P + alpha log r_S
    torch.testing.assert_close(
        unlabeled["demodice_reward"], unlabeled["log_ratio_performant"] + 0.1 * unlabeled["log_ratio_safe"]
    )
    assert demo_u.stepper.losses["dice"].tensor_keys.regularization == "unlabeled"
    assert demo_u.stepper.losses["dice"].tensor_keys.reward == "demodice_reward"
    assert demo_u.policy_loss.tensor_keys.role == "unlabeled"
    out = demo_u.stepper.step(None, buffers.sample())
    assert torch.isfinite(out["dice.loss_nu"]) and torch.isfinite(out["actor.loss_actor"])
    with demo_u.policy() as policy:
        td = policy(TensorDict({"observation": torch.zeros(3, 28)}, [3]))
    assert td["action"].shape == (3, 2)


def test_builder_trains_safedice_with_a_nonpreferred_role(tiny_pc1_dataset):
    from spoil_torchrl.algorithms import ALGORITHMS, BuildContext
    from spoil_torchrl.data import DualDemoBuffers, load_episodes
    from spoil_torchrl.objectives import safedice_auto_alpha

    episodes = load_episodes(f"file:{tiny_pc1_dataset}")
    roles = {"safe": torch.tensor([0, 1]), "performant": torch.tensor([6, 7]), "unlabeled": torch.arange(12)}
    cfg = _dice_baseline_cfg({"nonpreferred": 10.0}) | {"alpha": "auto", "standardize_reward": True}
    with pytest.raises(ValueError, match="nonpreferred"):
        ALGORITHMS["safedice"](
            cfg, BuildContext(DualDemoBuffers(episodes, roles, batch_size=64), 28, 2, progress=False)
        )

    # D_N: the unsafe-high and unsafe-medium episodes (ids 6-11 of the tiny file)
    buffers = DualDemoBuffers(episodes, roles | {"nonpreferred": torch.arange(6, 12)}, batch_size=64, seed=0)
    training = ALGORITHMS["safedice"](cfg, BuildContext(buffers, 28, 2, progress=False))
    unlabeled = buffers["unlabeled"].storage[:]
    probability = torch.sigmoid(unlabeled["log_ratio_nonpreferred"].double())
    alpha = training.diagnostics["alpha"]
    assert alpha == pytest.approx(safedice_auto_alpha(probability)) and 0.0 <= alpha < 1.0
    dice = training.stepper.losses["dice"]
    assert dice.alpha == alpha and dice.reward_std == pytest.approx(training.diagnostics["reward_std"])
    assert dice.reward_mean == pytest.approx(training.diagnostics["reward_mean"])
    out = training.stepper.step(None, buffers.sample())
    assert torch.isfinite(out["dice.loss_nu"]) and torch.isfinite(out["actor.loss_actor"])
    assert float(out["dice.clipped_fraction"]) == 0.0  # the auto alpha fits every unlabeled sample
    # a fixed alpha and no standardisation
    fixed = ALGORITHMS["safedice"](
        cfg | {"alpha": 0.2, "standardize_reward": False}, BuildContext(buffers, 28, 2, progress=False)
    )
    assert fixed.stepper.losses["dice"].alpha == 0.2 and fixed.stepper.losses["dice"].reward_std == 1.0


def test_step_every_steps_on_every_nth_call_and_keeps_its_count():
    from spoil_torchrl.trainers import StepEvery

    p = torch.nn.Parameter(torch.zeros(()))
    opt = StepEvery(torch.optim.SGD([p], lr=1.0), interval=2)
    for _ in range(5):
        opt.zero_grad()
        (-p).backward()
        opt.step()
    assert p.item() == 2.0 and opt.calls == 5  # stepped at calls 2 and 4
    other = StepEvery(torch.optim.SGD([torch.nn.Parameter(torch.zeros(()))], lr=1.0), interval=2)
    other.load_state_dict(opt.state_dict())
    assert other.calls == 5 and other.param_groups[0]["lr"] == 1.0
    with pytest.raises(ValueError, match="interval"):
        StepEvery(torch.optim.SGD([p], lr=1.0), interval=0)


def test_builder_trains_dwbc_s_jointly(tiny_pc1_dataset):
    from spoil_torchrl.algorithms import ALGORITHMS, BuildContext
    from spoil_torchrl.data import DualDemoBuffers, load_episodes
    from spoil_torchrl.objectives import DWBCLoss

    episodes = load_episodes(f"file:{tiny_pc1_dataset}")
    roles = {
        "safe": torch.tensor([0, 1, 3]),
        "performant": torch.tensor([6, 7]),
        "unlabeled": torch.arange(12),
    }
    buffers = DualDemoBuffers(episodes, roles, batch_size=64, seed=0)
    cfg = {
        "distribution": "normal",
        "hidden_cells": [16],
        "expert": "performant",
        "unlabeled": "safe",
        "alpha": 7.5,
        "eta": 0.5,
        "actor_lr": 1e-3,
        "discriminator": {"hidden_cells": [16], "lr": 1e-3, "update_interval": 3},
    }
    training = ALGORITHMS["dwbc_s"](cfg, BuildContext(buffers, 28, 2, progress=False))
    loss = training.policy_loss
    assert isinstance(loss, DWBCLoss) and training.stepper.losses == {"dwbc": loss}
    assert loss.tensor_keys.expert == "performant" and loss.tensor_keys.unlabeled == "safe"
    assert loss.alpha == 7.5 and loss.offset == 1.0  # the reference's offsets by default
    disc_before = [p.detach().clone() for p in loss.discriminator_network_params.values(True, True)]
    actor_before = [p.detach().clone() for p in loss.actor_network_params.values(True, True)]
    for step in range(3):
        out = training.stepper.step(None, buffers.sample())
        assert torch.isfinite(out["dwbc.loss_actor"]) and torch.isfinite(out["dwbc.loss_discriminator"])
        moved = any(
            not torch.equal(a, b)
            for a, b in zip(disc_before, loss.discriminator_network_params.values(True, True), strict=True)
        )
        assert moved == (step == 2)  # the discriminator steps on every third call only
    assert all(
        not torch.equal(a, b)
        for a, b in zip(actor_before, loss.actor_network_params.values(True, True), strict=True)
    )
    with training.policy() as policy:
        td = policy(TensorDict({"observation": torch.zeros(3, 28)}, [3]))
    assert td["action"].shape == (3, 2)
    with pytest.raises(ValueError, match="nonpreferred"):
        ALGORITHMS["dwbc_s"](
            cfg | {"unlabeled": "nonpreferred"}, BuildContext(buffers, 28, 2, progress=False)
        )


def test_builder_trains_coptidice_with_the_episode_constraint(tiny_pc1_dataset):
    from spoil_torchrl.algorithms import ALGORITHMS, BuildContext, EpisodeConstraint
    from spoil_torchrl.data import DualDemoBuffers, load_episodes
    from spoil_torchrl.objectives import per_step_cost_limit

    episodes = load_episodes(f"file:{tiny_pc1_dataset}")
    roles = {"safe": torch.tensor([0, 1]), "performant": torch.tensor([6, 7]), "unlabeled": torch.arange(12)}
    buffers = DualDemoBuffers(episodes, roles, batch_size=64, seed=0)
    cfg = {
        "distribution": "normal",
        "hidden_cells": [16],
        "gamma": 0.99,
        "alpha": 0.01,
        "cost_ub_epsilon": 0.01,
        "nu_gradient_penalty": 10.0,
        "init_lagrange": 1.0,
        "cost_limit": None,
        "nu_lr": 1e-3,
        "lagrange_lr": 1e-3,
        "actor_lr": 1e-3,
    }
    with pytest.raises(ValueError, match="cost limit"):
        ALGORITHMS["coptidice"](cfg, BuildContext(buffers, 28, 2, progress=False))
    constraint = EpisodeConstraint(cost_threshold=40.0, episode_length=500)
    training = ALGORITHMS["coptidice"](
        cfg, BuildContext(buffers, 28, 2, progress=False, constraint=constraint)
    )
    dice = training.stepper.losses["dice"]
    assert dice.cost_limit == pytest.approx(per_step_cost_limit(40.0, 500, 0.99))
    assert training.diagnostics["cost_limit"] == dice.cost_limit
    assert 0.0 <= training.diagnostics["cost_rate_unlabeled"] <= 1.0
    assert training.policy_loss.tensor_keys.role == "unlabeled"
    batch = buffers.sample()
    lagrange = dice.lagrange.item()
    out = training.stepper.step(None, batch)
    assert all(torch.isfinite(out[f"dice.{k}"]) for k in ("loss_nu", "loss_chi", "loss_tau", "loss_lagrange"))
    assert float(out["actor.weight_mean"]) == pytest.approx(1.0, rel=1e-5)
    assert dice.lagrange.item() != lagrange  # lambda has its optimiser
    fixed = ALGORITHMS["coptidice"](cfg | {"cost_limit": 0.05}, BuildContext(buffers, 28, 2, progress=False))
    assert fixed.stepper.losses["dice"].cost_limit == 0.05
