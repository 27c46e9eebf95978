"""Networks: shapes, distributions, clipping, deterministic evaluation."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from spoil_torchrl.modules import (
    ClippedTanhNormal,
    NormalParams,
    make_actor,
    make_discriminator,
    make_value_network,
)


@pytest.mark.parametrize("distribution", ["tanh_normal", "normal", "categorical"])
def test_actor_samples_and_scores(distribution):
    actor = make_actor(4, 3, hidden_cells=(8,), distribution=distribution)
    td = actor(TensorDict({"observation": torch.randn(6, 4)}, [6]))
    assert td["action"].shape == (6, 3)
    assert actor.get_dist(td).log_prob(td["action"]).shape == (6,)
    if distribution == "categorical":
        assert (td["action"].sum(-1) == 1).all()


def test_tanh_actor_respects_bounds_and_is_deterministic_in_eval():
    low, high = torch.tensor([-2.0, 0.0]), torch.tensor([2.0, 1.0])
    actor = make_actor(4, 2, hidden_cells=(8,), action_low=low, action_high=high)
    obs = TensorDict({"observation": torch.randn(100, 4) * 10}, [100])
    action = actor(obs.clone())["action"]
    assert ((action >= low) & (action <= high)).all()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        a1, a2 = actor(obs.clone())["action"], actor(obs.clone())["action"]
    torch.testing.assert_close(a1, a2)


def test_clipped_tanh_normal_scores_bounds_finitely():
    dist = ClippedTanhNormal(torch.zeros(3, 2), torch.ones(3, 2), low=-1.0, high=1.0)
    values = torch.tensor([[1.0, -1.0], [1.0, 1.0], [0.0, 0.5]])
    assert torch.isfinite(dist.log_prob(values)).all()
    # away from the bound it is the plain TanhNormal density
    inner = torch.tensor([[0.3, -0.2]])
    from torchrl.modules import TanhNormal

    torch.testing.assert_close(
        ClippedTanhNormal(torch.zeros(1, 2), torch.ones(1, 2)).log_prob(inner),
        TanhNormal(torch.zeros(1, 2), torch.ones(1, 2)).log_prob(inner),
    )


def test_normal_params_clip_log_std_and_mean():
    loc, scale = NormalParams(loc_bound=2.0)(torch.tensor([[5.0, 10.0], [-5.0, -10.0]]))
    assert loc.tolist() == [[2.0], [-2.0]]
    torch.testing.assert_close(scale, torch.exp(torch.tensor([[2.0], [-5.0]])))
    with pytest.raises(ValueError, match="log_std_min"):
        NormalParams(log_std_min=1.0, log_std_max=0.0)


def test_value_and_discriminator_shapes():
    td = TensorDict({"observation": torch.randn(5, 4), "action": torch.randn(5, 2)}, [5])
    assert make_value_network(4, hidden_cells=(8,))(td.clone())["nu"].shape == (5, 1)
    assert make_discriminator(4, 2, hidden_cells=(8,))(td.clone())["logit"].shape == (5, 1)


@pytest.mark.parametrize(
    ("factory", "args"),
    [(make_actor, (0, 2)), (make_value_network, (0,)), (make_discriminator, (3, 0))],
)
def test_bad_dimensions_raise(factory, args):
    with pytest.raises(ValueError, match="positive"):
        factory(*args)


def test_unknown_distribution_raises():
    with pytest.raises(ValueError, match="unknown distribution"):
        make_actor(3, 2, distribution="beta")
