"""PUDiscriminatorLoss, in the style of TorchRL's test/objectives."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from spoil_torchrl.modules import make_discriminator
from spoil_torchrl.objectives import LogRatio, PUDiscriminatorLoss, pu_log_ratio
from tests.conftest import ACT_DIM, OBS_DIM


def _loss(**kwargs) -> PUDiscriminatorLoss:
    return PUDiscriminatorLoss(make_discriminator(OBS_DIM, ACT_DIM, hidden_cells=(16, 16)), **kwargs)


def test_output_keys_and_scalars(batch):
    loss = _loss()
    out = loss(batch)
    assert set(out.keys()) == set(loss.out_keys)
    for key in out.keys():
        assert out[key].shape == torch.Size([])
    assert out["loss_gradient_penalty"] > 0


def test_losses_reach_only_discriminator_parameters(batch):
    loss = _loss()
    params = list(loss.parameters())
    assert len(params) == len(list(loss.discriminator_network_params.values(True, True)))
    for key in ("loss_positive", "loss_unlabeled", "loss_gradient_penalty"):
        loss.zero_grad()
        loss(batch)[key].backward()
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in params), key
    for role in ("performant", "unlabeled"):
        assert not batch[role, "observation"].requires_grad


def test_matches_logistic_objective_by_hand(batch):
    loss = _loss(gradient_penalty=0.0)
    out = loss(batch)
    net = loss.get_stateful_net("discriminator_network")
    with torch.no_grad():
        lp = net(batch["performant"].clone())["logit"]
        lu = net(batch["unlabeled"].clone())["logit"]
    expected_pos = -torch.log(torch.sigmoid(lp)).mean()
    expected_unl = -torch.log(1 - torch.sigmoid(lu)).mean()
    torch.testing.assert_close(out["loss_positive"], expected_pos, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out["loss_unlabeled"], expected_unl, rtol=1e-5, atol=1e-6)


def test_bad_reduction_and_arguments_raise():
    with pytest.raises(ValueError, match="reduction"):
        _loss(reduction="max")
    with pytest.raises(ValueError, match="class_prior"):
        _loss(class_prior=1.0)
    with pytest.raises(ValueError, match="gradient_penalty"):
        _loss(gradient_penalty=-1.0)


def test_gradient_penalty_is_differentiable(batch):
    loss = _loss(gradient_penalty=10.0)
    gp = loss(batch)["loss_gradient_penalty"]
    assert gp > 0
    grads = torch.autograd.grad(gp, list(loss.parameters()), allow_unused=True)
    assert any(g is not None and g.abs().sum() > 0 for g in grads)


def _categorical_problem():
    # Positive and unlabeled distributions over 4 one-hot "state-action" categories.
    p = torch.tensor([0.4, 0.3, 0.2, 0.1])
    u = torch.tensor([0.25, 0.25, 0.25, 0.25])
    return p, u


def _train_on_categories(loss: PUDiscriminatorLoss, p, u, steps: int = 1500) -> torch.Tensor:
    eye = torch.eye(4)
    optim = torch.optim.Adam(loss.parameters(), lr=0.05)
    for _ in range(steps):
        ip, iu = torch.multinomial(p, 512, True), torch.multinomial(u, 512, True)
        batch = TensorDict(
            {
                "performant": TensorDict({"observation": eye[ip], "action": torch.zeros(512, 1)}, [512]),
                "unlabeled": TensorDict({"observation": eye[iu], "action": torch.zeros(512, 1)}, [512]),
            },
            [],
        )
        out = loss(batch)
        optim.zero_grad()
        (out["loss_positive"] + out["loss_unlabeled"]).backward()
        optim.step()
    with torch.no_grad():
        query = TensorDict({"observation": eye, "action": torch.zeros(4, 1)}, [4])
        return loss.get_stateful_net("discriminator_network")(query)["logit"].squeeze(-1)


def test_optimal_logit_is_the_log_density_ratio():
    """Eq. (16)-(18): the trained logit estimates log(d_pos / d_U)."""
    p, u = _categorical_problem()
    loss = PUDiscriminatorLoss(make_discriminator(4, 1, hidden_cells=()), gradient_penalty=0.0)
    logit = _train_on_categories(loss, p, u)
    torch.testing.assert_close(logit, torch.log(p / u), atol=0.12, rtol=0)


def test_pu_form_recovers_the_ratio_through_pu_log_ratio():
    p, u = _categorical_problem()
    eta = 0.5
    loss = PUDiscriminatorLoss(
        make_discriminator(4, 1, hidden_cells=()), gradient_penalty=0.0, class_prior=eta
    )
    logit = _train_on_categories(loss, p, u)
    torch.testing.assert_close(pu_log_ratio(logit, eta), torch.log(p / u), atol=0.12, rtol=0)
    assert math.isclose(pu_log_ratio(torch.tensor(0.0), eta).item(), 0.0, abs_tol=1e-7)


def test_log_ratio_module_writes_without_gradients(batch):
    disc = make_discriminator(OBS_DIM, ACT_DIM, hidden_cells=(8,))
    td = LogRatio(disc)(batch["unlabeled"].clone())
    assert td["log_ratio_performant"].shape == (32, 1)
    assert not td["log_ratio_performant"].requires_grad


def test_pu_risk_stays_bounded_when_the_prior_is_too_large():
    """With eta * d_pos > d_U somewhere the unbiased PU risk is unbounded below; the non-negative one is not."""
    p, u = _categorical_problem()
    loss = PUDiscriminatorLoss(
        make_discriminator(4, 1, hidden_cells=()), gradient_penalty=0.0, class_prior=0.7
    )
    logit = _train_on_categories(loss, p, u, steps=800)
    assert logit.abs().max() < 15


def test_pu_mode_needs_mean_reduction_and_converts_log_ratios(batch):
    with pytest.raises(ValueError, match="reduction='mean'"):
        _loss(class_prior=0.5, reduction="none")
    loss = _loss(class_prior=0.5)
    loss(batch)
    module = loss.log_ratio_module()
    net = loss.get_stateful_net("discriminator_network")
    with torch.no_grad():
        logit = net(batch["unlabeled"].clone())["logit"]
    torch.testing.assert_close(
        module(batch["unlabeled"].clone())["log_ratio_performant"], pu_log_ratio(logit, 0.5)
    )
    plain = _loss().log_ratio_module("lr")
    assert plain.log_ratio_fn is None and plain.out_keys == ["lr"]


def test_gradient_penalty_is_the_two_sided_one_on_a_linear_discriminator(batch):
    # logit = w . [s, a] has input gradient w everywhere: the penalty is c * (|w| - 1)^2, not c * |w|^2
    disc = make_discriminator(OBS_DIM, ACT_DIM, hidden_cells=())
    with torch.no_grad():
        for p in disc.parameters():
            p.zero_()
        weight = next(p for p in disc.parameters() if p.ndim == 2)
        weight[0, 0] = 3.0  # |w| = 3
    out = PUDiscriminatorLoss(disc, gradient_penalty=2.0)(batch)
    torch.testing.assert_close(out["loss_gradient_penalty"], torch.tensor(2.0 * (3.0 - 1.0) ** 2))


def test_log_ratio_module_writes_the_discriminator_logit(batch):
    disc = make_discriminator(OBS_DIM, ACT_DIM, hidden_cells=(8,))
    td = batch["unlabeled"].clone()
    expected = disc(td.clone())["logit"].detach()
    torch.testing.assert_close(LogRatio(disc)(td)["log_ratio_performant"], expected)
    eta = 0.3
    pu = LogRatio(disc, out_key="r", log_ratio_fn=lambda logit: pu_log_ratio(logit, eta))(td)["r"]
    torch.testing.assert_close(pu, pu_log_ratio(expected, eta))
