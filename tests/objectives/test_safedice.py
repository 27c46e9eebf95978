"""SafeDICELoss, its reward and its "auto" alpha, in the style of TorchRL's test/objectives."""

from __future__ import annotations

import math

import pytest
import torch

from spoil_torchrl.modules import make_actor, make_discriminator, make_value_network
from spoil_torchrl.objectives import (
    PUDiscriminatorLoss,
    SafeDICELoss,
    WeightedBCLoss,
    safedice_auto_alpha,
    safedice_reward,
)
from tests.conftest import ACT_DIM, OBS_DIM, transitions

GAMMA, ALPHA = 0.9, 0.3


@pytest.fixture
def batch(batch):
    batch["unlabeled", "log_ratio_nonpreferred"] = torch.randn(32, 1)
    return batch


def _loss(**kwargs) -> SafeDICELoss:
    kwargs.setdefault("gamma", GAMMA)
    kwargs.setdefault("alpha", ALPHA)
    return SafeDICELoss(make_value_network(OBS_DIM, hidden_cells=(16, 16)), **kwargs)


def _mixture(alpha: float = ALPHA):
    """d_N, d_P on 6 points (d_P = 0 on the first two) and d_U = alpha d_N + (1 - alpha) d_P."""
    d_n = torch.tensor([0.3, 0.2, 0.2, 0.1, 0.2, 0.0], dtype=torch.float64)
    d_p = torch.tensor([0.0, 0.0, 0.1, 0.4, 0.2, 0.3], dtype=torch.float64)
    d_u = alpha * d_n + (1 - alpha) * d_p
    return d_n, d_p, d_u, d_n / (d_n + d_u)


def test_reward_recovers_the_preferred_ratio_on_an_exact_mixture():
    d_n, d_p, d_u, probability = _mixture()
    reward = safedice_reward(probability, ALPHA)
    positive = d_p > 0
    torch.testing.assert_close(reward[positive], torch.log(d_p / d_u)[positive])
    # where d_P = 0 the ratio is 0: the log is floored (the numerator rounds to ~0)
    assert bool((reward[~positive] < -15).all())
    # by the formula, away from the boundary
    d = torch.tensor([0.1, 0.4])
    torch.testing.assert_close(
        safedice_reward(d, 0.2), torch.log((1 - 1.2 * d) / ((1 - 0.2) * (1 - d))), rtol=1e-6, atol=1e-6
    )


def test_reward_is_guarded_beyond_the_mixture_bound():
    d = torch.linspace(0.0, 1.0, 101)
    reward = safedice_reward(d, 0.5)
    assert bool(torch.isfinite(reward).all())
    assert bool((reward[1:] <= reward[:-1] + 1e-6).all())  # non-increasing in D, even at D -> 1
    beyond = d >= 1 / 1.5
    torch.testing.assert_close(reward[beyond], reward[beyond][:1].expand(int(beyond.sum())))
    torch.testing.assert_close(safedice_reward(d, 0.0), torch.zeros(101))  # alpha = 0: r = 0
    for bad in (1.0, -0.1):
        with pytest.raises(ValueError, match="alpha"):
            safedice_reward(d, bad)


def test_auto_alpha_recovers_the_mixture_share_and_follows_the_reference():
    *_, probability = _mixture()
    # (1 - D) / D = alpha + (1 - alpha) d_P / d_N >= alpha, with equality where d_P = 0
    assert safedice_auto_alpha(probability) == pytest.approx(ALPHA - 1e-5, abs=1e-9)
    assert safedice_auto_alpha(torch.tensor([0.0, 0.1])) == pytest.approx(1 - 1e-5)  # cap, then margin
    assert safedice_auto_alpha(torch.tensor([0.2, 1.0])) == 0.0  # floored (D = 1 allows no d_N)
    assert safedice_auto_alpha(torch.tensor([0.5]), margin=0.0) == 1.0
    with pytest.raises(ValueError, match="at least one"):
        safedice_auto_alpha(torch.tensor([]))
    # with the auto alpha no unlabeled sample is clipped
    alpha = safedice_auto_alpha(probability)
    assert bool((probability <= 1 / (1 + alpha)).all())


def _advantage_by_hand(loss: SafeDICELoss, batch):
    nu = loss.get_stateful_net("nu_network")
    unl = batch["unlabeled"]
    with torch.no_grad():
        v = nu(unl.select("observation").clone())["nu"].squeeze(-1)
        v_next = nu(unl["next"].select("observation").clone())["nu"].squeeze(-1)
        v_init = nu(batch["init"].clone())["nu"].squeeze(-1)
    d = torch.sigmoid(unl["log_ratio_nonpreferred"].squeeze(-1))
    reward = torch.log((1 - (1 + loss.alpha) * d) / ((1 - loss.alpha) * (1 - d)))
    reward = (reward - loss.reward_mean) / loss.reward_std
    not_term = 1.0 - unl["next", "terminated"].float().squeeze(-1)
    return reward + GAMMA * v_next * not_term - v, v_init, reward


def test_output_keys_and_weights_written(batch):
    loss = _loss()
    out = loss(batch)
    assert set(out.keys()) == set(loss.out_keys)
    assert all(out[k].shape == torch.Size([]) for k in out.keys())
    w = batch["unlabeled", "dice_weight"]
    assert w.shape == (32, 1) and not w.requires_grad
    torch.testing.assert_close(w.mean(), torch.tensor(1.0))
    assert out["alpha"].item() == pytest.approx(ALPHA)


def test_weights_and_dual_match_safedice_by_hand(batch):
    batch["unlabeled", "log_ratio_nonpreferred"] = torch.randn(32, 1) - 2.0  # D well below 1 / (1 + alpha)
    loss = _loss(gradient_penalty=0.0, reward_mean=0.4, reward_std=2.0)
    out = loss(batch)
    adv, init_nu, reward = _advantage_by_hand(loss, batch)
    w_star = torch.exp(adv - 1.0)
    torch.testing.assert_close(batch["unlabeled", "dice_weight"].squeeze(-1), w_star / w_star.mean())
    torch.testing.assert_close(out["log_weight_mean"], torch.log(w_star.mean()))
    torch.testing.assert_close(
        out["loss_nu"], torch.log(torch.exp(adv).mean()) + (1 - GAMMA) * init_nu.mean()
    )
    torch.testing.assert_close(out["reward_mean"], reward.mean())
    assert out["clipped_fraction"].item() == 0.0


def test_reward_shift_leaves_the_weights_but_the_scale_does_not(batch):
    base = _loss(gradient_penalty=0.0)
    base(batch)
    w = batch["unlabeled", "dice_weight"].clone()
    shifted = _loss(gradient_penalty=0.0, reward_mean=3.0)
    shifted.load_state_dict(base.state_dict())
    shifted(batch)
    torch.testing.assert_close(batch["unlabeled", "dice_weight"], w)
    scaled = _loss(gradient_penalty=0.0, reward_std=3.0)
    scaled.load_state_dict(base.state_dict())
    scaled(batch)
    assert not torch.allclose(batch["unlabeled", "dice_weight"], w)


def test_clipped_samples_are_counted_and_finite(batch):
    batch["unlabeled", "log_ratio_nonpreferred"][:8] = 50.0  # D = 1 > 1 / (1 + alpha)
    out = _loss()(batch)
    assert out["clipped_fraction"].item() == pytest.approx(0.25)
    assert torch.isfinite(out["loss_nu"]) and torch.isfinite(batch["unlabeled", "dice_weight"]).all()


def test_each_loss_reaches_only_its_own_parameters(batch):
    dice = _loss()
    actor_loss = WeightedBCLoss(
        make_actor(OBS_DIM, ACT_DIM, hidden_cells=(8,)), role="unlabeled", weight="dice_weight"
    )
    nu_params = list(dice.nu_network_params.values(True, True))
    actor_params = list(actor_loss.parameters())
    assert set(map(id, dice.parameters())) == set(map(id, nu_params))
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
    torch.testing.assert_close(actor_out["weight_mean"], torch.tensor(1.0))


def test_the_discriminator_logit_is_not_trained_through_the_loss(batch):
    logit = batch["unlabeled", "log_ratio_nonpreferred"].requires_grad_(True)
    out = _loss()(batch)
    assert out["loss_nu"].requires_grad
    (grad,) = torch.autograd.grad(out["loss_nu"], [logit], allow_unused=True)
    assert grad is None


def test_with_a_nonpreferred_discriminator(batch):
    """The SafeDICE pipeline: C_N trained by PUDiscriminatorLoss(positive="nonpreferred"), frozen, annotated."""
    batch["nonpreferred"] = transitions(16)
    disc = PUDiscriminatorLoss(
        make_discriminator(OBS_DIM, ACT_DIM, hidden_cells=(8,)), positive="nonpreferred"
    )
    disc_out = disc(batch)
    sum(v for k, v in disc_out.items() if k.startswith("loss_")).backward()
    ratio = disc.log_ratio_module("log_ratio_nonpreferred")
    ratio(batch["unlabeled"])
    assert not batch["unlabeled", "log_ratio_nonpreferred"].requires_grad
    alpha = safedice_auto_alpha(torch.sigmoid(batch["unlabeled", "log_ratio_nonpreferred"]))
    out = _loss(alpha=alpha)(batch)
    assert out["clipped_fraction"].item() == 0.0 and torch.isfinite(out["loss_nu"])


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


def test_weights_do_not_overflow(batch):
    batch["unlabeled", "log_ratio_nonpreferred"][:] = -30.0  # r = -log(1 - alpha) everywhere
    out = _loss(gradient_penalty=0.0, reward_std=1e-3)(batch)  # a tiny scale makes A huge
    w = batch["unlabeled", "dice_weight"]
    assert torch.isfinite(w).all() and torch.isfinite(out["loss_nu"])


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("gamma", 0.0),
        ("gamma", 1.0),
        ("alpha", 1.0),
        ("alpha", -0.1),
        ("reward_std", 0.0),
        ("reward_std", math.nan),
    ],
)
def test_bad_hyper_parameters_raise(name, value):
    with pytest.raises(ValueError, match=name):
        _loss(**{name: value})


def test_gradient_penalty_nonzero_and_differentiable(batch):
    with_gp, without = _loss(gradient_penalty=10.0), _loss(gradient_penalty=0.0)
    without.load_state_dict(with_gp.state_dict())
    penalty = with_gp(batch)["loss_nu"] - without(batch)["loss_nu"]
    assert penalty > 0
    grads = torch.autograd.grad(penalty, list(with_gp.nu_network_params.values(True, True)))
    assert any(g.abs().sum() > 0 for g in grads)
