"""COptiDICELoss, its cost-limit conversion and its pieces, in the style of TorchRL's test/objectives."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from spoil_torchrl.modules import make_actor, make_value_network
from spoil_torchrl.objectives import (
    COptiDICELoss,
    WeightedBCLoss,
    coptidice_weight,
    per_step_cost_limit,
    soft_chi2,
    worst_case_weights,
)
from tests.conftest import ACT_DIM, OBS_DIM

GAMMA, ALPHA, LIMIT = 0.9, 0.5, 0.3


def _loss(**kwargs) -> COptiDICELoss:
    kwargs.setdefault("gamma", GAMMA)
    kwargs.setdefault("alpha", ALPHA)
    kwargs.setdefault("cost_limit", LIMIT)
    return COptiDICELoss(
        make_value_network(OBS_DIM, hidden_cells=(16, 16)),
        make_value_network(OBS_DIM, hidden_cells=(16, 16), out_key="chi"),
        **kwargs,
    )


def test_per_step_cost_limit_by_hand():
    # L = 40 over T = 500 steps at gamma = 0.99: (1 - 0.99^500) * 40 / 500
    assert per_step_cost_limit(40.0, 500, 0.99) == pytest.approx((1 - 0.99**500) * 0.08, rel=1e-12)
    assert per_step_cost_limit(40.0, 500, 0.99) == pytest.approx(0.0794743, rel=1e-6)
    # it is the normalised discounted occupancy cost of spending L evenly over the T steps of an episode
    limit, horizon, gamma = 25.0, 7, 0.8
    occupancy_cost = (1 - gamma) * sum(gamma**t * limit / horizon for t in range(horizon))
    assert per_step_cost_limit(limit, horizon, gamma) == pytest.approx(occupancy_cost, rel=1e-12)
    # OSRL's L (1 - gamma^T) / ((1 - gamma) T) is 1 / (1 - gamma) times larger (OSRL issue #28) ...
    osrl = limit * (1 - gamma**horizon) / (1 - gamma) / horizon
    assert per_step_cost_limit(limit, horizon, gamma) == pytest.approx((1 - gamma) * osrl, rel=1e-12)
    # ... and over a long horizon ours tends to L / T, the per-step budget of a continuing episode
    assert per_step_cost_limit(40.0, 5000, 0.99) == pytest.approx(40.0 / 5000, rel=1e-12)
    for args, match in (
        ((-1.0, 500, 0.99), "episode_limit"),
        ((40.0, 0, 0.99), "horizon"),
        ((40.0, 500, 1.0), "gamma"),
    ):
        with pytest.raises(ValueError, match=match):
            per_step_cost_limit(*args)


def test_closed_form_weight_maximises_the_inner_problem():
    """w* = (f')^{-1}(e / alpha) maximises w e - alpha f(w) over w >= 0 (soft-chi^2)."""
    grid = torch.linspace(0.0, 6.0, 600_001, dtype=torch.float64)
    for e in (-0.3, -0.01, 0.0, 0.02, 0.4):
        w = coptidice_weight(torch.tensor(e, dtype=torch.float64), ALPHA)
        best = grid[torch.argmax(grid * e - ALPHA * soft_chi2(grid))]
        assert float(w) == pytest.approx(float(best), abs=2e-5)
    torch.testing.assert_close(
        soft_chi2(torch.tensor([0.5, 2.0])), torch.tensor([0.5 * math.log(0.5) + 0.5, 0.5])
    )


def _values(loss: COptiDICELoss, batch):
    nu = loss.get_stateful_net("nu_network")
    chi = loss.get_stateful_net("chi_network")
    unl = batch["unlabeled"]
    out = {}
    with torch.no_grad():
        for name, net, key in (("nu", nu, "nu"), ("chi", chi, "chi")):
            out[name] = (
                net(batch["init"].clone())[key].squeeze(-1),
                net(unl.select("observation").clone())[key].squeeze(-1),
                net(unl["next"].select("observation").clone())[key].squeeze(-1),
            )
    return out


def test_losses_match_a_hand_computation(batch):
    loss = _loss(gradient_penalty=0.0, init_lagrange=0.7, init_tau=0.4)
    out = loss(batch)
    values = _values(loss, batch)
    unl = batch["unlabeled"]
    r, c = unl["next", "reward"].squeeze(-1), unl["next", "cost"].squeeze(-1)
    not_term = 1.0 - unl["next", "terminated"].float().squeeze(-1)
    lam, tau = 0.7, 0.4
    nu0, nu, nu_next = values["nu"]
    e = r - lam * c + GAMMA * not_term * nu_next - nu
    y = e / ALPHA
    w = torch.where(y < 0, torch.exp(y), y + 1)
    f = torch.where(w < 1, w * torch.log(w) - w + 1, 0.5 * (w - 1) ** 2)
    torch.testing.assert_close(out["loss_nu"], (1 - GAMMA) * nu0.mean() + (w * e - ALPHA * f).mean())
    chi0, chi, chi_next = values["chi"]
    ell = (1 - GAMMA) * chi0.mean() + w * (c + GAMMA * not_term * chi_next - chi)
    torch.testing.assert_close(out["loss_chi"], tau * torch.log(torch.exp(ell / tau).mean()))
    p = torch.softmax(ell / tau, dim=0) * ell.numel()
    kl = (p * torch.log(p)).mean()
    cost_ub = (p * w * c).mean()
    torch.testing.assert_close(out["kl"], kl)
    torch.testing.assert_close(out["cost_ub"], cost_ub)
    torch.testing.assert_close(out["cost_estimate"], (w * c).mean())
    torch.testing.assert_close(out["loss_tau"], tau * (0.01 - kl), rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(out["loss_lagrange"], lam * (LIMIT - cost_ub), rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(out["lagrange"], torch.tensor(lam))
    torch.testing.assert_close(out["weight_mean"], w.mean())
    torch.testing.assert_close(batch["unlabeled", "dice_weight"].squeeze(-1), w / w.mean())


def test_output_keys_and_weights_written(batch):
    loss = _loss()
    out = loss(batch)
    assert set(out.keys()) == set(loss.out_keys)
    assert all(out[k].shape == torch.Size([]) for k in out.keys())
    w = batch["unlabeled", "dice_weight"]
    assert w.shape == (32, 1) and not w.requires_grad
    torch.testing.assert_close(w.mean(), torch.tensor(1.0))
    assert out["cost_limit"].item() == pytest.approx(LIMIT)


def test_each_loss_reaches_only_its_own_parameters(batch):
    loss = _loss()
    actor_loss = WeightedBCLoss(
        make_actor(OBS_DIM, ACT_DIM, hidden_cells=(8,)), role="unlabeled", weight="dice_weight"
    )
    groups = {
        "loss_nu": list(loss.nu_network_params.values(True, True)),
        "loss_chi": list(loss.chi_network_params.values(True, True)),
        "loss_tau": [loss.tau_param],
        "loss_lagrange": [loss.lagrange_param],
    }
    assert set(map(id, loss.parameters())) == {id(p) for params in groups.values() for p in params}
    out, actor_out = loss(batch), actor_loss(batch)
    actor_params = list(actor_loss.parameters())
    everything = [p for params in groups.values() for p in params] + actor_params
    for name, own in [*groups.items(), ("loss_actor", actor_params)]:
        value = actor_out[name] if name == "loss_actor" else out[name]
        grads = torch.autograd.grad(value, everything, allow_unused=True, retain_graph=True)
        own_ids = set(map(id, own))
        for p, g in zip(everything, grads, strict=True):
            assert (g is not None) == (id(p) in own_ids), name
    torch.testing.assert_close(actor_out["weight_mean"], torch.tensor(1.0))


def test_lagrange_follows_the_cost_bound(batch):
    """Descent on loss_lagrange raises lambda when the bound exceeds the limit and lowers it otherwise; the
    reward is penalised by lambda * cost."""
    for limit, sign in ((0.0, -1.0), (100.0, 1.0)):
        loss = _loss(cost_limit=limit)
        (grad,) = torch.autograd.grad(loss(batch)["loss_lagrange"], [loss.lagrange_param])
        assert math.copysign(1.0, float(grad)) == sign
    low, high = _loss(init_lagrange=0.1, gradient_penalty=0.0), _loss(init_lagrange=5.0, gradient_penalty=0.0)
    high.load_state_dict({**low.state_dict(), "lagrange_param": high.lagrange_param.detach()})
    batch["unlabeled", "next", "cost"][:16] = 1.0
    batch["unlabeled", "next", "cost"][16:] = 0.0
    assert high(batch)["cost_estimate"] < low(batch)["cost_estimate"]  # weights move off the costly half


def test_epsilon_zero_uses_the_plain_estimate(batch):
    loss = _loss(cost_ub_epsilon=0.0)
    out = loss(batch)
    torch.testing.assert_close(out["cost_ub"], out["cost_estimate"])
    assert (
        out["loss_chi"].item() == 0.0 and out["loss_tau"].item() == 0.0 and not out["loss_chi"].requires_grad
    )


def test_worst_case_weights_tilt_toward_costly_samples(batch):
    """With chi = 0 the residual is w c (+ const): the KL-robust reweighting favours costly samples, so the
    upper bound is at least the plain estimate, and the tilt's KL matches KL(p || uniform)."""
    loss = _loss(init_tau=0.05)
    with torch.no_grad():
        for p in loss.chi_network_params.values(True, True):
            p.zero_()
    out = loss(batch)
    assert out["cost_ub"] > out["cost_estimate"]
    p, kl = worst_case_weights(torch.tensor([0.0, math.log(3.0)]), torch.tensor(1.0))
    torch.testing.assert_close(p, torch.tensor([0.5, 1.5]))
    torch.testing.assert_close(kl, torch.tensor(0.75 * math.log(1.5) + 0.25 * math.log(0.5)))


def test_terminated_stops_bootstrap_but_truncated_does_not(batch):
    loss = _loss(gradient_penalty=0.0)
    unl = batch["unlabeled"]
    unl["next", "terminated"][0] = True
    unl["next", "truncated"][1] = True
    loss(batch)
    w_before = unl["dice_weight"].clone()
    unl["next", "observation"][0] += 10.0
    loss(batch)
    torch.testing.assert_close(unl["dice_weight"], w_before)
    unl["next", "observation"][1] += 10.0
    loss(batch)
    assert not torch.allclose(unl["dice_weight"], w_before)


def test_weights_stay_finite_when_every_raw_weight_underflows(batch):
    batch["unlabeled", "next", "reward"][:] = -1e4  # e / alpha ~ -2e4: every exp underflows to 0
    out = _loss(alpha=0.01)(batch)
    w = batch["unlabeled", "dice_weight"]
    assert torch.isfinite(w).all() and torch.isfinite(out["loss_nu"])
    torch.testing.assert_close(w.mean(), torch.tensor(1.0))


def test_policy_extraction_is_weighted_bc_on_the_written_weights(batch):
    loss = _loss()
    actor_loss = WeightedBCLoss(
        make_actor(OBS_DIM, ACT_DIM, hidden_cells=(8,)), role="unlabeled", weight="dice_weight"
    )
    loss(batch)
    out = actor_loss(batch)
    actor = actor_loss.get_stateful_net("actor_network")
    unl = batch["unlabeled"]
    with torch.no_grad():
        log_prob = actor.get_dist(unl.select("observation").clone()).log_prob(unl["action"])
    torch.testing.assert_close(out["loss_actor"], -(unl["dice_weight"].squeeze(-1) * log_prob).mean())


def test_recovers_the_constrained_optimum_of_a_one_state_problem():
    """One state, two actions (logged 50/50) with r = (2, 0), c = (1, 0) and E_d[c] <= 0.5. The optimum puts
    d = (1/2, 1/2) (w = 1 on both) and needs lambda = 2 to make both actions equally good."""
    torch.manual_seed(0)
    obs = torch.zeros(2, OBS_DIM)
    unlabeled = TensorDict(
        {
            "observation": obs,
            "next": {
                "observation": obs.clone(),
                "reward": torch.tensor([[2.0], [0.0]]),
                "cost": torch.tensor([[1.0], [0.0]]),
                "terminated": torch.zeros(2, 1, dtype=torch.bool),
            },
        },
        [2],
    )
    batch = TensorDict({"unlabeled": unlabeled, "init": TensorDict({"observation": obs[:1]}, [1])}, [])
    loss = _loss(
        cost_limit=0.5, alpha=0.5, gamma=0.5, cost_ub_epsilon=0.0, gradient_penalty=0.0, init_lagrange=0.5
    )
    optimizer = torch.optim.Adam(loss.parameters(), lr=0.02)
    for _ in range(1500):
        out = loss(batch)
        optimizer.zero_grad()
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        optimizer.step()
    out = loss(batch)
    assert out["lagrange"].item() == pytest.approx(2.0, abs=0.05)
    assert out["weight_mean"].item() == pytest.approx(1.0, abs=0.02)
    assert out["cost_estimate"].item() == pytest.approx(0.5, abs=0.02)


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("gamma", 1.0),
        ("alpha", 0.0),
        ("cost_limit", -0.1),
        ("cost_limit", math.inf),
        ("cost_ub_epsilon", -0.1),
        ("gradient_penalty", -1.0),
        ("init_lagrange", 0.0),
        ("init_tau", -1.0),
    ],
)
def test_bad_hyper_parameters_raise(name, value):
    with pytest.raises(ValueError, match=name):
        _loss(**{name: value})


def test_set_keys_reads_another_cost(batch):
    loss = _loss()
    renamed = batch.clone()
    renamed.rename_key_("unlabeled", "pool")
    renamed["pool", "penalty"] = renamed["pool", "next", "cost"] * 2
    loss.set_keys(unlabeled="pool", cost="penalty", weight="w")
    assert ("pool", "penalty") in loss.in_keys and ("pool", "next", "reward") in loss.in_keys
    out = loss(renamed)
    assert ("pool", "w") in renamed.keys(True)
    assert out["cost_estimate"] > 0
    with pytest.raises(ValueError, match="not an accepted tensordict key"):
        loss.set_keys(logit="x")


def test_gradient_penalty_nonzero_and_differentiable(batch):
    with_gp, without = _loss(gradient_penalty=10.0), _loss(gradient_penalty=0.0)
    without.load_state_dict(with_gp.state_dict())
    a, b = with_gp(batch), without(batch)
    for key, params in (("loss_nu", with_gp.nu_network_params), ("loss_chi", with_gp.chi_network_params)):
        penalty = a[key] - b[key]
        assert penalty > 0
        grads = torch.autograd.grad(penalty, list(params.values(True, True)), retain_graph=True)
        assert any(g.abs().sum() > 0 for g in grads)
