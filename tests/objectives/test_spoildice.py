"""SpoilDICELoss (Eq. 7, 11, 12, 19), in the style of TorchRL's test/objectives."""

from __future__ import annotations

import pytest
import torch

from spoil_torchrl.modules import make_actor, make_value_network
from spoil_torchrl.objectives import SpoilDICELoss, WeightedBCLoss
from tests.conftest import ACT_DIM, OBS_DIM

GAMMA = 0.9


def _loss(**kwargs) -> SpoilDICELoss:
    kwargs.setdefault("gamma", GAMMA)
    return SpoilDICELoss(make_value_network(OBS_DIM, hidden_cells=(16, 16)), **kwargs)


def _advantage_by_hand(loss: SpoilDICELoss, batch) -> torch.Tensor:
    nu = loss.get_stateful_net("nu_network")
    unl = batch["unlabeled"]
    with torch.no_grad():
        v = nu(unl.select("observation").clone())["nu"].squeeze(-1)
        v_next = nu(unl["next"].select("observation").clone())["nu"].squeeze(-1)
    not_term = 1.0 - unl["next", "terminated"].float().squeeze(-1)
    return (
        unl["log_ratio_performant"].squeeze(-1)
        + loss.lagrange.detach() * unl["safe_support"].squeeze(-1)
        + GAMMA * v_next * not_term
        - v
    )


def test_output_keys_and_weights_written(batch):
    loss = _loss()
    out = loss(batch)
    assert set(out.keys()) == set(loss.out_keys)
    assert all(out[k].shape == torch.Size([]) for k in out.keys())
    w = batch["unlabeled", "dice_weight"]
    assert w.shape == (32, 1) and not w.requires_grad
    torch.testing.assert_close(w.mean(), torch.tensor(1.0))


def test_weights_match_closed_form_by_hand(batch):
    loss = _loss(init_lagrange=0.7, gradient_penalty=0.0)
    out = loss(batch)
    adv = _advantage_by_hand(loss, batch)
    w_star = torch.exp(adv - 1.0)  # Eq. (11)
    torch.testing.assert_close(batch["unlabeled", "dice_weight"].squeeze(-1), w_star / w_star.mean())
    torch.testing.assert_close(out["log_weight_mean"], torch.log(w_star.mean()))
    torch.testing.assert_close(out["advantage_mean"], adv.mean())


def test_dual_objective_matches_eq19_by_hand(batch):
    loss = _loss(init_lagrange=0.3, gradient_penalty=0.0)
    out = loss(batch)
    adv = _advantage_by_hand(loss, batch)
    nu = loss.get_stateful_net("nu_network")
    with torch.no_grad():
        init_nu = nu(batch["init"].clone())["nu"].mean()
    expected = (1 - GAMMA) * init_nu + torch.log(torch.exp(adv).mean()) - 0.3
    torch.testing.assert_close(out["loss_nu"], expected)
    torch.testing.assert_close(out["loss_lambda"], expected)


def test_lambda_gradient_is_eq12_at_normalised_weights(batch):
    loss = _loss(gradient_penalty=0.0)
    out = loss(batch)
    (grad,) = torch.autograd.grad(out["loss_lambda"], [loss.lagrange])
    w = batch["unlabeled", "dice_weight"].squeeze(-1)
    support = batch["unlabeled", "safe_support"].squeeze(-1)
    torch.testing.assert_close(grad, (w * support).mean() - 1.0)
    torch.testing.assert_close(out["support_weight"], (w * support).mean())


def test_each_loss_reaches_only_its_own_parameters(batch):
    dice = _loss()
    actor_loss = WeightedBCLoss(
        make_actor(OBS_DIM, ACT_DIM, hidden_cells=(8,)), role="unlabeled", weight="dice_weight"
    )
    nu_params = list(dice.nu_network_params.values(True, True))
    actor_params = list(actor_loss.parameters())
    out, actor_out = dice(batch), actor_loss(batch)

    def grads(loss_value):
        return torch.autograd.grad(
            loss_value, [*nu_params, dice.lagrange, *actor_params], allow_unused=True, retain_graph=True
        )

    n_nu = len(nu_params)
    g = grads(out["loss_nu"])
    assert all(x is not None for x in g[:n_nu]) and g[n_nu] is None and all(x is None for x in g[n_nu + 1 :])
    g = grads(out["loss_lambda"])
    assert all(x is None for x in g[:n_nu]) and g[n_nu] is not None and all(x is None for x in g[n_nu + 1 :])
    g = grads(actor_out["loss_actor"])
    assert all(x is None for x in g[: n_nu + 1]) and all(x is not None for x in g[n_nu + 1 :])


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
    batch["unlabeled", "log_ratio_performant"][0] = 1010.0
    out = _loss()(batch)
    w = batch["unlabeled", "dice_weight"]
    assert torch.isfinite(w).all() and torch.isfinite(out["loss_nu"])
    assert w[0].item() > 1000 * w[1].item()


def test_weights_stay_finite_across_a_thousand_nats(batch):
    # a shift by the batch minimum (instead of the maximum) would give exp(1000) = inf here
    batch["unlabeled", "log_ratio_performant"][:] = -500.0
    batch["unlabeled", "log_ratio_performant"][0] = 500.0
    out = _loss()(batch)
    w = batch["unlabeled", "dice_weight"]
    assert torch.isfinite(w).all() and torch.isfinite(out["loss_nu"]) and w.max() > 0
    assert int(w.argmax()) == 0


@pytest.mark.parametrize("gamma", [0.0, 1.0, -0.5])
def test_bad_gamma_raises(gamma):
    with pytest.raises(ValueError, match="gamma"):
        _loss(gamma=gamma)


def test_gradient_penalty_nonzero_and_differentiable(batch):
    with_gp, without = _loss(gradient_penalty=10.0), _loss(gradient_penalty=0.0)
    without.load_state_dict(with_gp.state_dict())
    penalty = with_gp(batch)["loss_nu"] - without(batch)["loss_nu"]
    assert penalty > 0
    grads = torch.autograd.grad(penalty, list(with_gp.nu_network_params.values(True, True)))
    assert any(g.abs().sum() > 0 for g in grads)


def test_state_dict_round_trip_includes_lambda(batch):
    a = _loss(init_lagrange=2.5, gradient_penalty=0.0)
    b = _loss(gradient_penalty=0.0)
    assert "lagrange" in a.state_dict()
    b.load_state_dict(a.state_dict())
    assert b.lagrange.item() == 2.5
    torch.testing.assert_close(a(batch)["loss_nu"], b(batch)["loss_nu"])


def test_lambda_grows_while_weight_sits_off_support(batch):
    batch["unlabeled", "safe_support"][:16] = 0.0
    batch["unlabeled", "safe_support"][16:] = 1.0
    loss = _loss(gradient_penalty=0.0)
    optim = torch.optim.Adam([loss.lagrange], lr=0.1)
    before = loss(batch)["support_weight"].item()
    for _ in range(50):
        optim.zero_grad()
        loss(batch)["loss_lambda"].backward()
        optim.step()
    out = loss(batch)
    assert loss.lagrange.item() > 3.0
    assert out["support_weight"].item() > max(before, 0.9)


def test_unbatched_init_role_is_a_clear_error(batch):
    from tensordict import TensorDict

    batch["init"] = TensorDict({"observation": torch.randn(8, OBS_DIM)}, [])
    with pytest.raises(ValueError, match="role 'init' has no batch dimension"):
        _loss()(batch)


def test_non_binary_support_and_flat_terminated_are_rejected(batch):
    bad_support = batch.clone()
    bad_support["unlabeled", "safe_support"] = torch.rand(32, 1)
    with pytest.raises(ValueError, match="0/1 indicator"):
        _loss()(bad_support)
    flat = batch.clone()
    flat["unlabeled"]["next"] = flat["unlabeled"]["next"].exclude("terminated")
    flat["unlabeled"]["next"].batch_size = []
    flat["unlabeled", "next", "terminated"] = torch.zeros(32, dtype=torch.bool)
    with pytest.raises(ValueError, match="trailing dimension of 1"):
        _loss()(flat)


def _two_constraint_batch(batch):
    """``batch`` with a second support indicator beside the first (``safe_support`` of shape ``[n, 2]``)."""
    first = batch["unlabeled", "safe_support"]
    second = (torch.arange(first.shape[0]) % 3 != 0).float().unsqueeze(-1)
    batch["unlabeled", "safe_support"] = torch.cat([first, second], dim=-1)
    return batch


def test_several_constraints_sum_their_multipliers_in_the_advantage_and_the_dual(batch):
    """K = 2: the advantage has lambda_1 1_1 + lambda_2 1_2 (docs/several_constraints.md), the dual subtracts
    lambda_1 + lambda_2, and lambda_k's gradient is E[w 1_k] - 1, each constraint's own."""
    batch = _two_constraint_batch(batch)
    loss = _loss(constraints=2, gradient_penalty=0.0)
    with torch.no_grad():
        loss.lagrange.copy_(torch.tensor([0.4, 1.1]))
    out = loss(batch)
    assert loss.lagrange.shape == (2,) and set(out.keys()) == set(loss.out_keys)
    support = batch["unlabeled", "safe_support"]
    nu = loss.get_stateful_net("nu_network")
    unl = batch["unlabeled"]
    with torch.no_grad():
        v = nu(unl.select("observation").clone())["nu"].squeeze(-1)
        v_next = nu(unl["next"].select("observation").clone())["nu"].squeeze(-1)
        init_nu = nu(batch["init"].clone())["nu"].mean()
    not_term = 1.0 - unl["next", "terminated"].float().squeeze(-1)
    adv = unl["log_ratio_performant"].squeeze(-1) + 0.4 * support[:, 0] + 1.1 * support[:, 1]
    adv = adv + GAMMA * v_next * not_term - v
    torch.testing.assert_close(out["advantage_mean"], adv.mean())
    expected = (1 - GAMMA) * init_nu + torch.log(torch.exp(adv).mean()) - 1.5
    torch.testing.assert_close(out["loss_lambda"], expected)
    (grad,) = torch.autograd.grad(out["loss_lambda"], [loss.lagrange])
    w = batch["unlabeled", "dice_weight"].squeeze(-1)
    torch.testing.assert_close(grad, (w[:, None] * support).mean(0) - 1.0)
    for k in range(2):
        torch.testing.assert_close(out[f"support_weight_{k}"], (w * support[:, k]).mean())
        torch.testing.assert_close(out[f"lagrange_{k}"], loss.lagrange[k].detach())
    both = support.prod(-1)
    torch.testing.assert_close(out["support_fraction"], both.mean())
    torch.testing.assert_close(out["support_weight"], (w * both).mean())


def test_one_constraint_of_several_is_the_single_constraint_loss(batch):
    """Two identical indicators with (lambda, 0) give the single-constraint loss at lambda."""
    single = _loss(init_lagrange=0.6, gradient_penalty=0.0)
    double = _loss(constraints=2, gradient_penalty=0.0)
    double.load_state_dict({**single.state_dict(), "lagrange": torch.tensor([0.6, 0.0])})
    out_single = single(batch.clone())
    support = batch["unlabeled", "safe_support"]
    batch["unlabeled", "safe_support"] = torch.cat([support, support], dim=-1)
    out_double = double(batch)
    for key in ("loss_nu", "loss_lambda", "support_weight", "advantage_mean"):
        torch.testing.assert_close(out_double[key], out_single[key])


def test_several_constraints_refuse_a_support_of_another_width_and_bad_counts(batch):
    with pytest.raises(ValueError, match=r"shape \(32, 1\); with constraints=2 .*\[32, 2\]"):
        _loss(constraints=2)(batch)
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="constraints must be an integer >= 1"):
            _loss(constraints=bad)
    from spoil_torchrl.objectives.support import check_supports_intersect

    disjoint = torch.tensor([[1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    with pytest.raises(ValueError, match=r"no transition is inside all 3 supports .*50.0 %, 50.0 %, 50.0 %"):
        check_supports_intersect(disjoint, "safe_support")
    check_supports_intersect(torch.cat([disjoint, torch.ones(1, 3)]), "safe_support")  # one row in all three
