"""DWBCLoss and its pieces, in the style of TorchRL's test/objectives."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from spoil_torchrl.modules import make_actor, make_discriminator
from spoil_torchrl.objectives import (
    DWBCLoss,
    dwbc_discriminator_loss,
    dwbc_expert_weight,
    dwbc_probability,
    dwbc_unlabeled_weight,
    log_prob_feature,
)
from tests.conftest import ACT_DIM, OBS_DIM, dual_batch

ALPHA, ETA = 7.5, 0.5


def _networks(hidden=(16,)):
    actor = make_actor(OBS_DIM, ACT_DIM, hidden_cells=hidden, distribution="normal")
    disc = make_discriminator(OBS_DIM, ACT_DIM, hidden_cells=hidden, extra_inputs={"policy_log_prob": 1})
    return actor, disc


def _loss(**kwargs) -> DWBCLoss:
    return DWBCLoss(*_networks(), **kwargs)


@pytest.fixture
def batch():
    return dual_batch(n_safe=4, n_perf=4, n_unl=4)  # equal role sizes, as the reference samples them


def test_weights_by_hand():
    d = torch.tensor([0.1, 0.3, 0.5, 0.9])
    # expert: alpha - eta / (d (1 - d)) - 1 (reference), without the - 1 (paper)
    expected = ALPHA - ETA / (d * (1 - d))
    torch.testing.assert_close(dwbc_expert_weight(d, ALPHA, ETA), expected - 1)
    torch.testing.assert_close(dwbc_expert_weight(d, ALPHA, ETA, offset=0.0), expected)
    assert float(dwbc_expert_weight(d, ALPHA, ETA).min()) == pytest.approx(7.5 - 1 - 0.5 / 0.09, abs=1e-5)
    # unlabeled: d / (1 - d) where d >= 0.5, else 0 (reference); 1 / (1 - d) or 1 (paper)
    torch.testing.assert_close(dwbc_unlabeled_weight(d), torch.tensor([0.0, 0.0, 1.0, 9.0]))
    torch.testing.assert_close(dwbc_unlabeled_weight(d, offset=0.0), torch.tensor([1.0, 1.0, 2.0, 10.0]))


def test_probability_is_clipped_and_discriminator_loss_by_hand():
    d = dwbc_probability(torch.tensor([-50.0, -1.0, 0.5, 50.0]))
    torch.testing.assert_close(
        d, torch.tensor([0.1, torch.sigmoid(torch.tensor(-1.0)), 0.6225, 0.9]), atol=1e-4, rtol=0
    )
    d_e, d_u = torch.tensor([0.8, 0.6]), torch.tensor([0.3, 0.7, 0.2])
    expected = (
        -(math.log(0.8) + math.log(0.6)) / 2
        + (math.log(0.2) + math.log(0.4)) / 2
        - (math.log(0.7) + math.log(0.3) + math.log(0.8)) / 3 / ETA
    )
    assert dwbc_discriminator_loss(d_e, d_u, ETA).item() == pytest.approx(expected, rel=1e-6)
    # the PU risk is eta times smaller than this (the reference's scaling)
    pu = ETA * -torch.log(d_e).mean() - torch.log(1 - d_u).mean() - ETA * -torch.log(1 - d_e).mean()
    torch.testing.assert_close(dwbc_discriminator_loss(d_e, d_u, ETA), pu / ETA)


def _by_hand(loss: DWBCLoss, batch, offset: float = 1.0):
    """The reference code's ``DWBC.train`` on the same batch, written out."""
    actor = loss.get_stateful_net("actor_network")
    disc = loss.get_stateful_net("discriminator_network")
    out = {}
    with torch.no_grad():
        for name, role in (("e", batch["performant"]), ("o", batch["unlabeled"])):
            log_pi = actor.get_dist(role.select("observation").clone()).log_prob(role["action"])
            feature = ((log_pi / ACT_DIM).clamp(-20, 10) + 20) / 30
            td = TensorDict({"observation": role["observation"], "action": role["action"]}, role.batch_size)
            td["policy_log_prob"] = feature.unsqueeze(-1)
            out[name] = (log_pi, torch.sigmoid(disc(td)["logit"].squeeze(-1)).clamp(0.1, 0.9))
    (log_pi_e, d_e), (log_pi_o, d_o) = out["e"], out["o"]
    d_loss = torch.mean(-torch.log(d_e) + (-torch.log(1 - d_o) / ETA + torch.log(1 - d_e)))
    d_o_cut = d_o.clone()
    d_o_cut[d_o_cut < 0.5] = 0.0
    bc_loss = -log_pi_e
    corr_loss_e = -log_pi_e * (ETA / (d_e * (1.0 - d_e)) + offset)
    corr_loss_o = -log_pi_o * (1.0 / (1.0 - d_o_cut) - offset)
    p_loss = ALPHA * bc_loss.mean() - corr_loss_e.mean() + corr_loss_o.mean()
    return d_loss, p_loss, d_e, d_o


@pytest.mark.parametrize("reference_offsets", [True, False])
def test_losses_match_the_reference_by_hand(batch, reference_offsets):
    loss = _loss(reference_offsets=reference_offsets)
    out = loss(batch)
    d_loss, p_loss, d_e, d_o = _by_hand(loss, batch, offset=1.0 if reference_offsets else 0.0)
    torch.testing.assert_close(out["loss_discriminator"], d_loss)
    torch.testing.assert_close(out["loss_actor"], p_loss)
    torch.testing.assert_close(out["d_expert"], d_e.mean())
    torch.testing.assert_close(out["unlabeled_kept"], (d_o >= 0.5).float().mean())


def test_output_keys_are_scalars(batch):
    loss = _loss()
    out = loss(batch)
    assert set(out.keys()) == set(loss.out_keys)
    assert all(out[k].shape == torch.Size([]) for k in out.keys())
    assert 0.1 <= out["d_expert"].item() <= 0.9 and out["expert_weight_mean"].item() > 0


def test_each_loss_reaches_only_its_own_parameters(batch):
    loss = _loss()
    actor_params = list(loss.actor_network_params.values(True, True))
    disc_params = list(loss.discriminator_network_params.values(True, True))
    assert set(map(id, loss.parameters())) == set(map(id, actor_params + disc_params))
    out = loss(batch)

    def grads(value):
        return torch.autograd.grad(value, [*actor_params, *disc_params], allow_unused=True, retain_graph=True)

    n = len(actor_params)
    g = grads(out["loss_discriminator"])  # the policy enters only through the detached log-prob feature
    assert all(x is None for x in g[:n]) and all(x is not None for x in g[n:])
    g = grads(out["loss_actor"])  # D is detached in the weights
    assert all(x is not None for x in g[:n]) and all(x is None for x in g[n:])


def test_the_policy_feature_changes_the_discriminator(batch):
    """D sees log pi: the same (s, a) scored under another policy gets another D."""
    loss = _loss()
    before = loss(batch)["d_unlabeled"]
    with torch.no_grad():
        for p in loss.actor_network_params.values(True, True):
            p.add_(torch.randn_like(p))
    assert not torch.allclose(loss(batch)["d_unlabeled"], before)
    assert log_prob_feature(torch.tensor([-1e9, 1e9]), 2).tolist() == [0.0, 1.0]


def test_dwbc_s_roles_and_set_keys(batch):
    loss = _loss(expert="performant", unlabeled="safe")  # DWBC-S
    assert ("safe", "action") in loss.in_keys and ("performant", "observation") in loss.in_keys
    assert ("unlabeled", "observation") not in loss.in_keys
    expected = loss(batch)["loss_actor"]
    renamed = batch.clone()
    renamed.rename_key_("performant", "expert_demos")
    renamed.rename_key_("safe", "pool")
    loss.set_keys(expert="expert_demos", unlabeled="pool")
    torch.testing.assert_close(loss(renamed)["loss_actor"], expected)
    with pytest.raises(ValueError, match="not an accepted tensordict key"):
        loss.set_keys(nonpreferred="x")


def test_a_discriminator_without_the_policy_input_is_a_clear_error(batch):
    actor = make_actor(OBS_DIM, ACT_DIM, hidden_cells=(8,))
    loss = DWBCLoss(actor, make_discriminator(OBS_DIM, ACT_DIM, hidden_cells=(8,)))
    with pytest.raises(KeyError, match="policy_log_prob"):
        loss(batch)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"eta": 0.0}, "eta"),
        ({"eta": 1.0}, "eta"),
        ({"alpha": 5.0}, "alpha=5.0 is too small"),  # 5 - 1 - 0.5 / 0.09 < 0
        ({"alpha": math.nan}, "alpha"),
    ],
)
def test_bad_hyper_parameters_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        _loss(**kwargs)
    _loss(alpha=6.0, reference_offsets=False)  # 6 - 0.5 / 0.09 >= 0 is fine without the offsets


def test_joint_training_keeps_the_expert_like_samples_and_clones_them():
    """D_E acts near +0.6; half of D_U acts like it, half near -0.6. Trained jointly, D keeps (D >= 0.5) the
    expert-like half of D_U and cuts the other, and the policy's mean moves to the expert's action."""
    torch.manual_seed(0)
    actor, disc = _networks(hidden=(16,))
    loss = DWBCLoss(actor, disc, expert="expert", unlabeled="offline")
    optimizer = torch.optim.Adam(loss.parameters(), lr=1e-2)

    def role(n, sign):
        action = (sign.unsqueeze(-1) * 0.6 + 0.05 * torch.randn(n, ACT_DIM)).clamp(-1, 1)
        return TensorDict({"observation": torch.randn(n, OBS_DIM), "action": action}, [n])

    def sample():
        signs = torch.where(torch.rand(64) < 0.5, 1.0, -1.0)
        return TensorDict({"expert": role(64, torch.ones(64)), "offline": role(64, signs)}, [])

    for _ in range(300):
        out = loss(sample())
        optimizer.zero_grad()
        (out["loss_discriminator"] + out["loss_actor"]).backward()
        optimizer.step()
    batch = sample()
    out = loss(batch)
    assert 0.35 <= out["unlabeled_kept"].item() <= 0.65
    offline = batch["offline"]
    with torch.no_grad():
        d = torch.stack(
            [
                loss(TensorDict({"expert": batch["expert"], "offline": offline[i : i + 1]}, []))[
                    "d_unlabeled"
                ]
                for i in range(64)
            ]
        )
    expert_like = offline["action"][:, 0] > 0
    assert float(d[expert_like].min()) >= 0.5 > float(d[~expert_like].max())
    with torch.no_grad(), loss.actor_network_params.to_module(loss.actor_network):
        mean = loss.actor_network.get_dist(batch["expert"].select("observation")).mean
    assert float(mean.mean()) > 0.4
