"""Which data each builder fits its pre-training on: wiring mistakes that leave every shape right."""

from __future__ import annotations

import pytest
import torch

from spoil_torchrl.algorithms import ALGORITHMS, BuildContext, dice
from spoil_torchrl.data import DualDemoBuffers, load_episodes


def _buffers(dataset) -> DualDemoBuffers:
    episodes = load_episodes(f"file:{dataset}")
    # safe: safe-high 0-2; performant: unsafe-high 6-8; unlabeled: all twelve (ids by policy type)
    roles = {"safe": torch.arange(0, 3), "performant": torch.arange(6, 9), "unlabeled": torch.arange(12)}
    return DualDemoBuffers(episodes, roles, batch_size=128, seed=0)


def _spoildice_cfg(kappa: float) -> dict:
    return {
        "distribution": "normal",
        "hidden_cells": [16],
        "gamma": 0.99,
        "kappa": kappa,
        "nu_gradient_penalty": 0.0,
        "init_lagrange": 0.0,
        "nu_lr": 1e-3,
        "lagrange_lr": 1e-3,
        "actor_lr": 1e-3,
        "discriminator": {
            "hidden_cells": [32],
            "gradient_penalty": {"performant": 0.0, "safe": 0.0},
            "lr": 3e-3,
            "steps": 200,
        },
    }


def test_spoildice_fits_its_support_cut_on_the_safe_demonstrations(tiny_pc1_dataset):
    # Eq. (13): the cut is the kappa-quantile of C_S's log-ratio over D_S, so it keeps 1 - kappa of D_S
    # (ties aside); a cut fitted on D_U would keep 1 - kappa of D_U and far more of D_S, which C_S ranks high.
    buffers = _buffers(tiny_pc1_dataset)
    ALGORITHMS["spoildice"](_spoildice_cfg(kappa=0.5), BuildContext(buffers, 28, 2, progress=False))
    unlabeled = buffers["unlabeled"].storage[:]
    kept = unlabeled["safe_support"].reshape(-1).bool()
    in_safe = torch.isin(unlabeled["episode"].reshape(-1), torch.arange(0, 3))
    assert 0.5 <= kept[in_safe].float().mean() < 0.55
    assert kept.float().mean() < 0.5  # D_U holds much that C_S ranks below the safe median


def test_demodice_s_trains_its_discriminator_against_the_safe_demonstrations(tiny_pc1_dataset, monkeypatch):
    calls = []
    real = dice.train_discriminators

    def spy(*args, **kwargs):
        calls.append(kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr(dice, "train_discriminators", spy)  # where the DICE builders call it
    cfg = _spoildice_cfg(kappa=0.01) | {"alpha": 0.1, "nu_gradient_penalty": 1e-4}
    cfg["discriminator"] = cfg["discriminator"] | {"steps": 2}
    ALGORITHMS["demodice_s"](cfg, BuildContext(_buffers(tiny_pc1_dataset), 28, 2, progress=False))
    assert len(calls) == 1 and calls[0]["positives"] == ("performant",) and calls[0]["against"] == "safe"
    calls.clear()
    ALGORITHMS["demodice_u"](cfg, BuildContext(_buffers(tiny_pc1_dataset), 28, 2, progress=False))
    assert len(calls) == 1 and calls[0].get("against", "unlabeled") == "unlabeled"


def test_fbc_with_the_oracle_support_keeps_exactly_the_safe_trajectories_of_d_p(tiny_pc1_dataset):
    import pytest

    from spoil_torchrl.algorithms import EpisodeConstraint
    from spoil_torchrl.data import episode_stats
    from spoil_torchrl.runs.settings import SettingsError

    episodes = load_episodes(f"file:{tiny_pc1_dataset}")
    cost = episode_stats(episodes)["cost"]
    # D_P: the three safe-high and the three unsafe-high episodes
    roles = {
        "safe": torch.arange(0, 3),
        "performant": torch.cat([torch.arange(0, 3), torch.arange(6, 9)]),
        "unlabeled": torch.arange(12),
    }
    buffers = DualDemoBuffers(episodes, roles, batch_size=128, seed=0)
    cfg = {
        "distribution": "normal",
        "hidden_cells": [16],
        "actor_lr": 1e-3,
        "kappa": 0.01,
        "support": "oracle",
    }
    training = ALGORITHMS["fbc"](
        cfg, BuildContext(buffers, 28, 2, progress=False, constraint=EpisodeConstraint(25.0, 500))
    )
    stored = buffers["performant"].storage[:]
    expected = (cost[stored["episode"]] <= 25.0).float()
    assert stored["safe_support"].shape == stored["next", "reward"].shape
    assert torch.equal(stored["safe_support"].reshape(-1), expected)
    assert 0 < float(expected.mean()) < 1  # both kinds present: the test can tell the weights apart
    assert training.diagnostics["support_share_performant"] == pytest.approx(float(expected.mean()))
    with pytest.raises(SettingsError, match="expected estimated or oracle"):
        ALGORITHMS["fbc"]({**cfg, "support": "true"}, BuildContext(buffers, 28, 2, progress=False))
    with pytest.raises(ValueError, match="needs the cost limit"):
        ALGORITHMS["fbc"](cfg, BuildContext(buffers, 28, 2, progress=False))


def test_a_stored_pretraining_rebuilds_the_same_main_stage_without_training(tiny_pc1_dataset, monkeypatch):
    """The pre-training's value holds what the main stage reads: written into fresh buffers, it gives the same
    annotations and diagnostics, and the main stage builds without training a discriminator."""
    from spoil_torchrl.algorithms import Pretraining

    cfg = _spoildice_cfg(kappa=0.05)
    algorithm = ALGORITHMS["spoildice"]
    buffers = _buffers(tiny_pc1_dataset)
    stage = algorithm.pretrain(cfg, BuildContext(buffers, 28, 2, progress=False))
    assert set(stage.annotations) == {"unlabeled", "performant"}
    assert set(stage.networks) == {"C_performant", "C_safe"}
    with pytest.raises(TypeError):  # read-only
        stage.annotations["unlabeled"]["safe_support"] = None

    def trained(*args, **kwargs):
        raise AssertionError("the main stage trained a discriminator")

    monkeypatch.setattr(dice, "train_discriminators", trained)
    fresh = _buffers(tiny_pc1_dataset)
    loaded = Pretraining(**stage.as_state())
    loaded.apply(fresh)
    for role, keys in stage.annotations.items():
        for key, value in keys.items():
            assert torch.equal(fresh[role].storage[:][key], value), (role, key)
    training = algorithm.main(cfg, BuildContext(fresh, 28, 2, progress=False), loaded)
    assert training.diagnostics == dict(stage.diagnostics) and training.dice is not None

    wrong = Pretraining({"unlabeled": {"safe_support": stage.annotations["unlabeled"]["safe_support"][:5]}})
    with pytest.raises(ValueError, match="'safe_support' has 5 rows, but role 'unlabeled' stores"):
        wrong.apply(fresh)


def test_one_constraint_through_the_per_constraint_path_is_todays_spoildice_bit_for_bit(tiny_pc1_dataset):
    """K = 1 (docs/several_constraints.md): a single safe set given as the constraint role ``safe_a`` (one C_S^k,
    one kappa cut, SpoilDICELoss(constraints=1)) trains the same networks as today's SpoilDICE given it as D_S,
    bit for bit: pre-training, annotations, and the dual and policy after 30 steps."""
    episodes = load_episodes(f"file:{tiny_pc1_dataset}")
    runs = {}
    for safe_role in ("safe", "safe_a"):
        roles = {
            safe_role: torch.arange(0, 3),
            "performant": torch.arange(6, 9),
            "unlabeled": torch.arange(12),
        }
        buffers = DualDemoBuffers(episodes, roles, batch_size=128, seed=0)
        torch.manual_seed(0)
        training = ALGORITHMS["spoildice"](
            _spoildice_cfg(kappa=0.1), BuildContext(buffers, 28, 2, progress=False)
        )
        for _ in range(30):
            training.stepper.step(None, buffers.sample())
        runs[safe_role] = (buffers["unlabeled"].storage[:], training)
    (plain, ours), (per_constraint, theirs) = runs["safe"], runs["safe_a"]
    assert torch.equal(plain["safe_support"], per_constraint["safe_support"])
    assert plain["safe_support"].float().mean() < 1.0  # the cut drops some of D_U
    assert torch.equal(plain["log_ratio_performant"], per_constraint["log_ratio_performant"])
    assert torch.equal(ours.dice.lagrange.reshape(-1), theirs.dice.lagrange.reshape(-1))
    assert float(ours.dice.lagrange.detach().reshape(-1)[0]) != 0.0  # it moved
    for mine, other in ((ours.policy_loss, theirs.policy_loss), (ours.dice, theirs.dice)):
        a, b = mine.state_dict(), other.state_dict()
        assert a.keys() == b.keys() and all(torch.equal(a[k].reshape(-1), b[k].reshape(-1)) for k in a)
