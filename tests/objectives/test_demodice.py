"""DemoDICELoss (DemoDICE-S / DemoDICE-U), in the style of TorchRL's test/objectives."""

from __future__ import annotations

import math

import pytest
import torch

from spoil_torchrl.modules import make_actor, make_value_network
from spoil_torchrl.objectives import DemoDICELoss, SpoilDICELoss, WeightedBCLoss
from tests.conftest import ACT_DIM, OBS_DIM

GAMMA, ALPHA = 0.9, 0.1


def _loss(**kwargs) -> DemoDICELoss:
    kwargs.setdefault("gamma", GAMMA)
    kwargs.setdefault("alpha", ALPHA)
    return DemoDICELoss(make_value_network(OBS_DIM, hidden_cells=(16, 16)), **kwargs)


def _advantage_by_hand(
    loss: DemoDICELoss, batch, role: str = "unlabeled", reward: str = "log_ratio_performant"
):
    nu = loss.get_stateful_net("nu_network")
    data = batch[role]
    with torch.no_grad():
        v = nu(data.select("observation").clone())["nu"].squeeze(-1)
        v_next = nu(data["next"].select("observation").clone())["nu"].squeeze(-1)
        v_init = nu(batch["init"].clone())["nu"].squeeze(-1)
    not_term = 1.0 - data["next", "terminated"].float().squeeze(-1)
    return data[reward].squeeze(-1) + GAMMA * v_next * not_term - v, v_init


def test_output_keys_and_weights_written(batch):
    loss = _loss()
    out = loss(batch)
    assert set(out.keys()) == set(loss.out_keys)
    assert all(out[k].shape == torch.Size([]) for k in out.keys())
    assert all(not out[k].requires_grad for k in out.keys() if not k.startswith("loss_"))
    w = batch["unlabeled", "dice_weight"]
    assert w.shape == (32, 1) and not w.requires_grad
    torch.testing.assert_close(w.mean(), torch.tensor(1.0))


def test_weights_and_dual_match_demodice_by_hand(batch):
    loss = _loss(gradient_penalty=0.0)
    out = loss(batch)
    adv, init_nu = _advantage_by_hand(loss, batch)
    w_star = torch.exp(adv / (1 + ALPHA) - 1.0)  # w* = d*/d_R, closed form
    torch.testing.assert_close(batch["unlabeled", "dice_weight"].squeeze(-1), w_star / w_star.mean())
    torch.testing.assert_close(out["log_weight_mean"], torch.log(w_star.mean()))
    expected = (1 + ALPHA) * torch.log(torch.exp(adv / (1 + ALPHA)).mean()) + (1 - GAMMA) * init_nu.mean()
    torch.testing.assert_close(out["loss_nu"], expected)
    torch.testing.assert_close(out["advantage_mean"], adv.mean())
    torch.testing.assert_close(out["reward_mean"], batch["unlabeled", "log_ratio_performant"].mean())
    w = w_star / w_star.mean()
    torch.testing.assert_close(out["effective_sample_size"], w.sum() ** 2 / (w**2).sum() / 32)


def test_alpha_zero_is_spoildice_without_support_term(batch):
    """With alpha = 0 and lambda = 0 both duals are log E[exp(A)] + (1 - gamma) E[nu(s0)] on the same A."""
    demo = _loss(alpha=0.0, gradient_penalty=0.0)
    spoil = SpoilDICELoss(
        make_value_network(OBS_DIM, hidden_cells=(16, 16)), gamma=GAMMA, gradient_penalty=0.0
    )
    spoil.load_state_dict(demo.state_dict() | {"lagrange": torch.tensor(0.0)})
    a = demo(batch)["loss_nu"]
    w_demo = batch["unlabeled", "dice_weight"].clone()
    torch.testing.assert_close(a, spoil(batch)["loss_nu"])
    torch.testing.assert_close(w_demo, batch["unlabeled", "dice_weight"])


def test_demodice_s_reads_the_safe_role_and_bc_extracts_there(batch):
    batch["safe", "log_ratio_performant_safe"] = torch.randn(16, 1)
    loss = _loss(regularization="safe", reward="log_ratio_performant_safe", gradient_penalty=0.0)
    assert ("safe", "log_ratio_performant_safe") in loss.in_keys
    assert not any(key[0] == "unlabeled" for key in loss.in_keys)
    out = loss(batch)
    adv, init_nu = _advantage_by_hand(loss, batch, role="safe", reward="log_ratio_performant_safe")
    w_star = torch.exp(adv / (1 + ALPHA))
    torch.testing.assert_close(batch["safe", "dice_weight"].squeeze(-1), w_star / w_star.mean())
    assert "dice_weight" not in batch["unlabeled"].keys()
    expected = (1 + ALPHA) * torch.log(torch.exp(adv / (1 + ALPHA)).mean()) + (1 - GAMMA) * init_nu.mean()
    torch.testing.assert_close(out["loss_nu"], expected)
    actor = WeightedBCLoss(make_actor(OBS_DIM, ACT_DIM, hidden_cells=(8,)), role="safe", weight="dice_weight")
    torch.testing.assert_close(actor(batch)["weight_mean"], torch.tensor(1.0))


def test_each_loss_reaches_only_its_own_parameters(batch):
    dice = _loss()
    actor_loss = WeightedBCLoss(
        make_actor(OBS_DIM, ACT_DIM, hidden_cells=(8,)), role="unlabeled", weight="dice_weight"
    )
    nu_params = list(dice.nu_network_params.values(True, True))
    actor_params = list(actor_loss.parameters())
    assert set(map(id, dice.parameters())) == set(map(id, nu_params))  # nu is the loss's only parameter set
    out, actor_out = dice(batch), actor_loss(batch)

    def grads(loss_value):
        return torch.autograd.grad(
            loss_value, [*nu_params, *actor_params], allow_unused=True, retain_graph=True
        )

    n_nu = len(nu_params)
    g = grads(out["loss_nu"])
    assert all(x is not None for x in g[:n_nu]) and all(x is None for x in g[n_nu:])
    g = grads(actor_out["loss_actor"])
    assert all(x is None for x in g[:n_nu]) and all(x is not None for x in g[n_nu:])


def test_the_reward_is_not_trained_through_the_loss(batch):
    reward = batch["unlabeled", "log_ratio_performant"].requires_grad_(True)
    out = _loss()(batch)
    (grad,) = torch.autograd.grad(out["loss_nu"], [reward], allow_unused=True)
    assert grad is None  # a discriminator that wrote it with gradients would still not be updated


def test_terminated_stops_bootstrap_but_truncated_does_not(batch):
    loss = _loss(gradient_penalty=0.0)
    unl = batch["unlabeled"]
    unl["next", "terminated"][0] = True
    unl["next", "truncated"][1] = True
    loss(batch)
    w_before = unl["dice_weight"].clone()
    unl["next", "observation"][0] += 10.0  # ignored: terminated
    loss(batch)
    torch.testing.assert_close(unl["dice_weight"], w_before)
    unl["next", "observation"][1] += 10.0  # used: truncated steps bootstrap
    loss(batch)
    assert not torch.allclose(unl["dice_weight"], w_before)


def test_weights_do_not_overflow(batch):
    batch["unlabeled", "log_ratio_performant"][:] = 1000.0
    batch["unlabeled", "log_ratio_performant"][0] = 1011.0
    out = _loss()(batch)
    w = batch["unlabeled", "dice_weight"]
    assert torch.isfinite(w).all() and torch.isfinite(out["loss_nu"])
    assert w[0].item() > 1000 * w[1].item()  # exp(11 / 1.1) ~ 2e4


@pytest.mark.parametrize(
    ("name", "value"), [("gamma", 0.0), ("gamma", 1.0), ("alpha", -0.1), ("alpha", math.nan)]
)
def test_bad_hyper_parameters_raise(name, value):
    with pytest.raises(ValueError, match=name):
        _loss(**{name: value})


def test_the_constructor_s_role_arguments_are_its_keys(batch):
    built = _loss(regularization="pool", reward="r")
    assert built.tensor_keys.regularization == "pool" and built.tensor_keys.reward == "r"
    with pytest.raises(KeyError, match="no role 'nonexistent'"):
        _loss(regularization="nonexistent")(batch)


def test_flat_terminated_is_rejected(batch):
    flat = batch.clone()
    flat["unlabeled"]["next"] = flat["unlabeled"]["next"].exclude("terminated")
    flat["unlabeled"]["next"].batch_size = []
    flat["unlabeled", "next", "terminated"] = torch.zeros(32, dtype=torch.bool)
    with pytest.raises(ValueError, match="trailing dimension of 1"):
        _loss()(flat)


def test_gradient_penalty_nonzero_and_differentiable(batch):
    with_gp, without = _loss(gradient_penalty=10.0), _loss(gradient_penalty=0.0)
    without.load_state_dict(with_gp.state_dict())
    penalty = with_gp(batch)["loss_nu"] - without(batch)["loss_nu"]
    assert penalty > 0
    grads = torch.autograd.grad(penalty, list(with_gp.nu_network_params.values(True, True)))
    assert any(g.abs().sum() > 0 for g in grads)


def test_nu_descent_lowers_the_dual(batch):
    loss = _loss(gradient_penalty=0.0)
    optim = torch.optim.Adam(loss.parameters(), lr=1e-2)
    first = loss(batch)["loss_nu"].item()
    for _ in range(30):
        optim.zero_grad()
        loss(batch)["loss_nu"].backward()
        optim.step()
    assert loss(batch)["loss_nu"].item() < first
