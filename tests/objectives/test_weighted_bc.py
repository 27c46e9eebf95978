"""WeightedBCLoss (Eq. 20): BC, filtered BC and DICE extraction as one loss."""

from __future__ import annotations

import pytest
import torch

from spoil_torchrl.modules import make_actor, make_value_network
from spoil_torchrl.objectives import SpoilDICELoss, WeightedBCLoss
from tests.conftest import ACT_DIM, OBS_DIM


def _actor(distribution="tanh_normal"):
    return make_actor(OBS_DIM, ACT_DIM, hidden_cells=(16,), distribution=distribution)


def _log_prob(loss: WeightedBCLoss, role_td) -> torch.Tensor:
    actor = loss.get_stateful_net("actor_network")
    with torch.no_grad():
        return actor.get_dist(role_td.select("observation").clone()).log_prob(role_td["action"])


def test_plain_bc_is_mean_negative_log_likelihood(batch):
    loss = WeightedBCLoss(_actor())
    out = loss(batch)
    torch.testing.assert_close(out["loss_actor"], -_log_prob(loss, batch["performant"]).mean())
    assert out["weight_mean"] == 1


def test_weights_multiply_the_nll_and_are_detached(batch):
    loss = WeightedBCLoss(_actor(), role="performant", weight="safe_support")
    w = batch["performant", "safe_support"]
    w.requires_grad_(True)
    out = loss(batch)
    expected = -(w.detach().squeeze(-1) * _log_prob(loss, batch["performant"])).mean()
    torch.testing.assert_close(out["loss_actor"], expected)
    out["loss_actor"].backward()
    assert w.grad is None
    assert all(p.grad is not None for p in loss.parameters())


def test_actions_on_the_bound_have_finite_likelihood(batch):
    batch["performant", "action"][:4] = 1.0
    batch["performant", "action"][4:8] = -1.0
    out = WeightedBCLoss(_actor())(batch)
    assert torch.isfinite(out["loss_actor"])
    out["loss_actor"].backward()


@pytest.mark.parametrize("distribution", ["tanh_normal", "normal"])
def test_bc_fits_the_demonstrated_action(distribution):
    torch.manual_seed(0)
    from tensordict import TensorDict

    obs = torch.randn(256, OBS_DIM)
    action = torch.tanh(obs[:, :ACT_DIM])  # a deterministic expert
    batch = TensorDict({"performant": TensorDict({"observation": obs, "action": action}, [256])}, [])
    loss = WeightedBCLoss(make_actor(OBS_DIM, ACT_DIM, hidden_cells=(64, 64), distribution=distribution))
    optim = torch.optim.Adam(loss.parameters(), lr=3e-3)
    for _ in range(400):
        optim.zero_grad()
        loss(batch)["loss_actor"].backward()
        optim.step()
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    actor = loss.get_stateful_net("actor_network")
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        predicted = actor(TensorDict({"observation": obs}, [256]))["action"]
    assert (predicted - action).abs().mean() < 0.1


def test_set_keys_role_weight_and_unknown(batch):
    loss = WeightedBCLoss(_actor(), role="unlabeled", weight="safe_support")
    assert ("unlabeled", "safe_support") in loss.in_keys
    loss.set_keys(weight=None)
    assert loss.tensor_keys.weight is None
    assert ("unlabeled", "safe_support") not in loss.in_keys
    loss.set_keys(role="safe")
    assert loss(batch)["weight_mean"] == 1
    with pytest.raises(ValueError, match="not an accepted tensordict key"):
        loss.set_keys(observation="obs")


def test_rejects_a_deterministic_module():
    from tensordict.nn import TensorDictModule

    with pytest.raises(TypeError, match="get_dist"):
        WeightedBCLoss(TensorDictModule(torch.nn.Linear(3, 2), in_keys=["observation"], out_keys=["action"]))


def test_a_dice_weight_no_dice_loss_has_written_is_named(batch):
    loss = WeightedBCLoss(_actor(), role="unlabeled", weight="dice_weight")
    with pytest.raises(KeyError, match=r"role 'unlabeled' has no entry 'dice_weight' \(a DICE loss"):
        loss(batch)  # before SpoilDICELoss has annotated D_U
    SpoilDICELoss(make_value_network(OBS_DIM, hidden_cells=(8,)))(
        batch
    )  # writes ("unlabeled", "dice_weight")
    assert torch.isfinite(loss(batch)["loss_actor"])
