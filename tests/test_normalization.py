"""Observation standardisation: statistics, the data copy, and the policy that carries them into a file."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from spoil_torchrl.data import fit_observation_normalizer, standardize_observations
from spoil_torchrl.modules import (
    ObservationNormalizer,
    make_actor,
    observation_normalizer_of,
    with_observation_norm,
)
from spoil_torchrl.zoo import load_policy, save_policy
from spoil_torchrl.zoo.policy_files import PolicyFileError, weights_digest

OBS, ACT = 28, 2


def _episodes(n: int = 40) -> TensorDict:
    obs = torch.randn(n, OBS) * torch.linspace(0.01, 10.0, OBS) + torch.linspace(-5.0, 5.0, OBS)
    return TensorDict(
        {
            "observation": obs,
            "next": {"observation": obs + 0.1, "reward": torch.ones(n, 1)},
            "action": torch.zeros(n, ACT),
            "episode": torch.arange(n) // 10,
        },
        [n],
    )


def test_fit_uses_the_given_episodes_and_standardises_to_unit_scale():
    episodes = _episodes()
    norm = fit_observation_normalizer(episodes, torch.tensor([0, 1]))
    first = episodes["observation"][:20]
    torch.testing.assert_close(norm.loc, first.mean(0))
    torch.testing.assert_close(norm.scale, first.std(0, unbiased=False) + 1e-3)
    out = standardize_observations(episodes, fit_observation_normalizer(episodes))
    torch.testing.assert_close(out["observation"].mean(0), torch.zeros(OBS), atol=1e-4, rtol=0)
    std = episodes["observation"].std(0, unbiased=False)
    # unit scale, except where the 1e-3 added to a tiny std (the first dimension's ~0.01) shows
    torch.testing.assert_close(out["observation"].std(0, unbiased=False), std / (std + 1e-3))
    # s' is standardised with the same statistics, the rest is untouched (and the input is not modified)
    torch.testing.assert_close(out["next", "observation"] - out["observation"], 0.1 / norm_scale(episodes))
    assert out["next", "reward"] is episodes["next", "reward"]
    assert not torch.equal(out["observation"], episodes["observation"])


def norm_scale(episodes: TensorDict) -> torch.Tensor:
    return fit_observation_normalizer(episodes).scale.expand(episodes.shape[0], OBS)


def test_normalizer_rejects_bad_statistics():
    with pytest.raises(ValueError, match="positive"):
        ObservationNormalizer(torch.zeros(3), torch.tensor([1.0, 0.0, 1.0]))
    with pytest.raises(ValueError, match="same shape"):
        ObservationNormalizer(torch.zeros(3), torch.ones(2))
    with pytest.raises(ValueError, match="no observations"):
        ObservationNormalizer.from_observations(torch.zeros(0, 3))


@pytest.mark.parametrize("distribution", ["tanh_normal", "normal"])
def test_saved_policy_acts_identically_after_load_policy(tmp_path, distribution):
    torch.manual_seed(0)
    episodes = _episodes()
    norm = fit_observation_normalizer(episodes)
    actor = make_actor(OBS, ACT, hidden_cells=(16, 16), distribution=distribution)
    policy = with_observation_norm(actor, norm)
    assert observation_normalizer_of(policy) is norm and observation_normalizer_of(actor) is None
    path = save_policy(tmp_path / "p.pt", policy, env_id="SafetyPointCircle1-v0", distribution=distribution)
    loaded, meta = load_policy(path, env_id="SafetyPointCircle1-v0")
    assert meta["observation_norm"] is True
    raw = episodes["observation"] * 3.0  # raw observations, as the environment gives them
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        a_saved = policy(TensorDict({"observation": raw}, [raw.shape[0]]))["action"]
        a_loaded = loaded(TensorDict({"observation": raw}, [raw.shape[0]]))["action"]
        a_inner = actor(TensorDict({"observation": norm(raw)}, [raw.shape[0]]))["action"]
    assert torch.equal(a_saved, a_loaded)
    assert torch.equal(a_saved, a_inner)
    # the wrapper shares the actor's layers: training one trains the other
    with torch.no_grad():
        next(actor.parameters()).add_(1.0)
    assert torch.equal(next(actor.parameters()), next(policy.parameters()))


def test_policy_without_normalizer_still_loads_and_corrupt_statistics_are_refused(tmp_path):
    actor = make_actor(OBS, ACT, hidden_cells=(8,))
    _, meta = load_policy(save_policy(tmp_path / "plain.pt", actor, env_id="SafetyPointCircle1-v0"))
    assert meta["observation_norm"] is False
    policy = with_observation_norm(actor, ObservationNormalizer.identity(OBS))
    with pytest.raises(ValueError, match="already"):
        with_observation_norm(policy, ObservationNormalizer.identity(OBS))
    path = save_policy(tmp_path / "norm.pt", policy, env_id="SafetyPointCircle1-v0")
    raw = torch.load(path, weights_only=True)
    scale_key = next(k for k in raw["actor"] if k.endswith("scale"))
    raw["actor"][scale_key][0] = 0.0
    torch.save(raw, path)
    with pytest.raises(PolicyFileError, match="checksum"):  # changed after saving: damaged
        load_policy(path)
    # written that way (checksum and all): the statistics themselves are bad
    raw["weights_sha256"] = weights_digest(raw["actor"])
    torch.save(raw, path)
    with pytest.raises(PolicyFileError, match="observation statistics are invalid.*positive"):
        load_policy(path)
