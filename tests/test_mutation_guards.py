"""Boundaries and determinism of the labelling and metrics: tests written against the survivors of a mutation
run (docs/mutation.md lists what each one guards)."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from spoil_torchrl.data.labeling import (
    controlled_mix,
    corrupt,
    draw,
    ilsp_return_threshold,
    replay_subsets,
    stats_table,
)
from spoil_torchrl.eval import aggregate_over_seeds, episode_metrics, mean_of_last


def _stats(returns, costs):
    return TensorDict({"return": torch.tensor(returns), "cost": torch.tensor(costs)}, [len(returns)])


def test_draw_accepts_zero_and_all_and_refuses_more():
    ids = torch.arange(5)
    assert draw(ids, 0, seed=0).numel() == 0
    assert sorted(draw(ids, 5, seed=0).tolist()) == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError, match="cannot draw 6"):
        draw(ids, 6, seed=0)
    assert draw([3, 1, 2], 3, seed=0).dtype == torch.int64


def test_return_quantile_zero_is_the_lowest_safe_return():
    stats = _stats([5.0, 2.0, 9.0, 50.0], [0.0, 1.0, 3.0, 99.0])
    assert ilsp_return_threshold(stats, cost_threshold=3.0, return_quantile=0.0) == 2.0


def test_stats_table_thresholds_are_inclusive_and_empty_roles_are_listed():
    stats = _stats([1.0, 3.0, 2.0], [5.0, 9.0, 0.0])  # episode 0 at the cost bound, 2 at the return bound
    table = stats_table(stats, {"all": torch.tensor([0, 1, 2]), "none": [], "last": [2]}, 5.0, 2.0)
    rows = table.splitlines()
    assert rows[0].startswith("| dataset | safe ratio") and rows[1] == "|---|---|---|---|---|"
    assert rows[2] == "| all | 0.67 | 0.67 | 0.33 | 3 |"
    assert rows[3] == "| none | - | - | - | 0 |" and rows[4] == "| last | 1.00 | 1.00 | 1.00 | 1 |"


def test_replay_subsets_thresholds_are_inclusive():
    stats = _stats([9.0, 10.0, 3.0], [4.0, 7.0, 0.0])
    roles = replay_subsets(stats, cost_threshold=4.0, safe_optimal_return=10.0, return_fraction=0.9)
    assert roles["safe"].tolist() == [0, 2] and roles["performant"].tolist() == [0, 1]


def _pools():
    return {
        "safe-high": torch.arange(0, 10),
        "safe-medium": torch.arange(10, 20),
        "unsafe-high": torch.arange(20, 30),
        "unsafe-medium": torch.arange(30, 40),
    }


def test_controlled_mix_is_seeded_and_splits_a_remainder_over_the_first_pools():
    kwargs = dict(n_safe=4, performance=0.5, n_performant=4, safeness=0.25, n_unlabeled=7)
    a, b = controlled_mix(_pools(), **kwargs, seed=3), controlled_mix(_pools(), **kwargs, seed=3)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert any(not torch.equal(a[k], controlled_mix(_pools(), **kwargs, seed=4)[k]) for k in a)
    assert not torch.equal(controlled_mix(_pools(), **kwargs)["safe"], a["safe"])  # default seed 0
    per_pool = [int(((a["unlabeled"] >= lo) & (a["unlabeled"] < lo + 10)).sum()) for lo in (0, 10, 20, 30)]
    assert per_pool == [2, 2, 2, 1]
    assert a["unlabeled"].dtype == torch.int64
    with pytest.raises(ValueError, match="pool 'safe-high' has 10 trajectories, 12 are needed"):
        controlled_mix(_pools(), n_safe=10, performance=1.0, n_performant=2, safeness=1.0)
    with pytest.raises(ValueError, match="n_unlabeled=41"):
        controlled_mix(_pools(), n_safe=1, performance=1.0, n_performant=1, safeness=0.0, n_unlabeled=41)
    with pytest.raises(ValueError, match="safeness"):
        controlled_mix(_pools(), n_safe=1, performance=1.0, n_performant=1, safeness=1.5)


def test_corrupt_is_seeded():
    safe, unsafe = torch.arange(10), torch.arange(100, 120)
    assert torch.equal(corrupt(safe, unsafe, 0.3, seed=1), corrupt(safe, unsafe, 0.3, seed=1))
    assert not torch.equal(corrupt(safe, unsafe, 0.3, seed=1), corrupt(safe, unsafe, 0.3, seed=2))
    with pytest.raises(ValueError, match="rate"):
        corrupt(safe, unsafe, 1.5)


def test_mean_of_last_accepts_one_and_a_column():
    assert mean_of_last([1.0, 2.0, 4.0], last=1) == 4.0
    assert mean_of_last(torch.tensor([[1.0], [3.0]]), last=2) == 2.0
    with pytest.raises(ValueError, match="smaller `last`"):
        mean_of_last([1.0], last=2)


def test_two_seeds_have_a_standard_error():
    agg = aggregate_over_seeds([[1.0], [3.0]], last=1)
    assert agg.stderr == pytest.approx(math.sqrt(2.0) / math.sqrt(2.0))
    assert math.isnan(aggregate_over_seeds([[1.0]], last=1).stderr)


def test_episode_metrics_reads_a_trailing_singleton_mask_and_names_a_bad_row():
    td = TensorDict(
        {
            "next": {"reward": torch.ones(2, 3, 1), "cost": torch.zeros(2, 3, 1)},
            "mask": torch.tensor([[True, True, False], [True, True, True]]).unsqueeze(-1),
        },
        [2, 3],
    )
    metrics = episode_metrics(td, cost_threshold=1.0)
    assert metrics["length"].tolist() == [2, 3] and metrics["length"].dtype == torch.int64
    assert metrics["return"].tolist() == [2.0, 3.0]
    td["mask"] = torch.tensor([[True, True, True], [True, False, True]]).unsqueeze(-1)
    with pytest.raises(ValueError, match="episode row 1 is not a prefix"):
        episode_metrics(td, cost_threshold=1.0)
    td["mask"] = torch.ones(2, 3, 2, dtype=torch.bool)
    with pytest.raises(ValueError, match=r"shape \[episodes, steps\]; got \[2, 3, 2\]"):
        episode_metrics(td[:, :], cost_threshold=1.0)


# -- objectives -----------------------------------------------------------------------------------------------

#: The keys of a flat DICE batch, for :func:`spoil_torchrl.objectives.keys.dice_transitions`.
DICE_KEYS = dict(
    role="unlabeled",
    init="init",
    state_keys=["observation"],
    next_key="next",
    terminated_key=("next", "terminated"),
    loss_name="X",
)


def test_interpolate_returns_points_on_each_segment():
    from spoil_torchrl.objectives.functional import interpolate

    torch.manual_seed(0)
    a, b = torch.randn(64, 3) + 5.0, torch.randn(64, 3) - 5.0
    x = interpolate(a, b)
    t = (x - b) / (a - b)  # the same t in [0, 1] for every coordinate of a row
    assert torch.allclose(t, t[:, :1].expand_as(t), atol=1e-5)
    assert bool(((t >= 0) & (t <= 1)).all()) and t[:, 0].std() > 0.1
    assert x.dtype == a.dtype
    double = interpolate(a.double(), b.double())
    assert double.dtype == torch.float64


def _linear_nu(weight):
    from tensordict.nn import TensorDictModule

    from spoil_torchrl.modules import make_value_network

    nu = make_value_network(5, hidden_cells=())
    with torch.no_grad():
        for p in nu.parameters():
            p.zero_()
        next(p for p in nu.parameters() if p.ndim == 2)[0, 0] = weight
    assert isinstance(nu, TensorDictModule)
    return nu


def test_gradient_penalty_forms():
    from spoil_torchrl.objectives.functional import gradient_penalty

    norms = torch.tensor([1.0, 3.0])
    assert gradient_penalty(norms, target=None).item() == 5.0  # E|g|^2
    assert gradient_penalty(norms, target=1.0).item() == 2.0  # E(|g| - 1)^2


@pytest.mark.parametrize("name", ["spoildice", "demodice", "safedice"])
def test_the_nu_penalty_adds_c_times_the_squared_gradient_norm(name, batch):
    # a linear nu with |grad| = 3 everywhere: loss_nu(c) - loss_nu(0) = c * 9
    from spoil_torchrl.objectives import DemoDICELoss, SafeDICELoss, SpoilDICELoss

    make = {
        "spoildice": lambda nu, c: SpoilDICELoss(nu, gradient_penalty=c),
        "demodice": lambda nu, c: DemoDICELoss(
            nu, gradient_penalty=c, regularization="safe", reward="log_ratio_performant"
        ),
        "safedice": lambda nu, c: SafeDICELoss(nu, alpha=0.5, gradient_penalty=c),
    }[name]
    if name == "safedice":
        batch["unlabeled", "log_ratio_nonpreferred"] = torch.randn(32, 1)
    with_penalty = make(_linear_nu(3.0), 0.5)(batch.clone())["loss_nu"]
    without = make(_linear_nu(3.0), 0.0)(batch.clone())["loss_nu"]
    torch.testing.assert_close(with_penalty - without, torch.tensor(0.5 * 9.0), rtol=1e-4, atol=1e-4)


def test_documented_defaults_of_the_losses():
    from spoil_torchrl.modules import make_actor, make_discriminator, make_value_network
    from spoil_torchrl.objectives import (
        COptiDICELoss,
        DemoDICELoss,
        DWBCLoss,
        PUDiscriminatorLoss,
        SafeDICELoss,
        SpoilDICELoss,
    )

    def nu():
        return make_value_network(5, hidden_cells=(8,))

    spoil = SpoilDICELoss(nu())
    assert (spoil.gamma, spoil.gradient_penalty, spoil.lagrange.item()) == (0.99, 1e-4, 0.0)
    demo = DemoDICELoss(nu())
    assert (demo.gamma, demo.gradient_penalty, demo.alpha) == (0.99, 1e-4, 0.1)
    safe = SafeDICELoss(nu(), alpha=0.0)  # alpha = 0 is allowed: no correction from D_N
    assert (safe.gamma, safe.gradient_penalty, safe.reward_mean, safe.reward_std) == (0.99, 1e-6, 0.0, 1.0)
    cop = COptiDICELoss(nu(), nu(), cost_limit=0.1)
    assert (cop.gamma, cop.gradient_penalty, cop.alpha, cop.cost_ub_epsilon) == (0.99, 1e-4, 0.01, 0.01)
    assert (cop.lagrange.item(), cop.tau.item()) == pytest.approx((1.0, 1.0))
    assert PUDiscriminatorLoss(make_discriminator(5, 2, hidden_cells=(8,))).gradient_penalty == 10.0
    dwbc = DWBCLoss(
        make_actor(5, 2, hidden_cells=(8,)),
        make_discriminator(5, 2, hidden_cells=(8,), extra_inputs={"policy_log_prob": 1}),
    )
    assert (dwbc.alpha, dwbc.eta, dwbc.offset) == (7.5, 0.5, 1.0)  # reference offsets on by default


def test_loss_argument_boundaries():
    from spoil_torchrl.modules import make_actor, make_discriminator, make_value_network
    from spoil_torchrl.objectives import COptiDICELoss, DWBCLoss, PUDiscriminatorLoss, per_step_cost_limit

    disc = make_discriminator(5, 2, hidden_cells=(8,))
    with pytest.raises(ValueError, match="class_prior"):
        PUDiscriminatorLoss(disc, class_prior=0.0)
    dwbc_disc = make_discriminator(5, 2, hidden_cells=(8,), extra_inputs={"policy_log_prob": 1})
    with pytest.raises(ValueError, match="eta"):
        DWBCLoss(make_actor(5, 2, hidden_cells=(8,)), dwbc_disc, eta=1.0)
    # the expert weight alpha - eta / (D (1 - D)) - 1 must stay >= 0 at D = 0.1: alpha >= 0.5 / 0.09 + 1
    bound = 0.5 / (0.1 * 0.9) + 1.0
    DWBCLoss(make_actor(5, 2, hidden_cells=(8,)), dwbc_disc, alpha=bound + 1e-6)
    with pytest.raises(ValueError, match=f"use alpha >= {bound:.3f}"):
        DWBCLoss(make_actor(5, 2, hidden_cells=(8,)), dwbc_disc, alpha=bound - 0.01)
    DWBCLoss(
        make_actor(5, 2, hidden_cells=(8,)), dwbc_disc, alpha=bound - 1.0 + 1e-6, reference_offsets=False
    )
    with pytest.raises(TypeError, match="probabilistic actor"):
        DWBCLoss(disc, dwbc_disc)
    assert per_step_cost_limit(0.0, 1, 0.99) == 0.0 and per_step_cost_limit(10.0, 1, 0.5) == pytest.approx(
        5.0
    )
    with pytest.raises(ValueError, match="gamma"):
        COptiDICELoss(
            make_value_network(5, hidden_cells=(8,)),
            make_value_network(5, hidden_cells=(8,)),
            cost_limit=0.1,
            gamma=0.0,
        )


def test_dice_transitions_accepts_one_transition_and_refuses_flat_flags():
    from spoil_torchrl.objectives.keys import dice_transitions

    one = TensorDict(
        {
            "unlabeled": TensorDict(
                {
                    "observation": torch.randn(1, 3),
                    "next": {
                        "observation": torch.randn(1, 3),
                        "terminated": torch.zeros(1, 1, dtype=torch.bool),
                    },
                },
                [1],
            ),
            "init": TensorDict({"observation": torch.randn(1, 3)}, [1]),
        },
        [],
    )
    keys = DICE_KEYS
    out = dice_transitions(one, **keys)
    assert out.batch_shape == torch.Size([1]) and out.init["observation"].shape == (1, 3)
    one["unlabeled", "next", "terminated"] = torch.zeros(1, 1, dtype=torch.bool).squeeze(-1)
    with pytest.raises(ValueError, match="trailing dimension of 1"):
        dice_transitions(one, **keys)


def test_log_ratio_module_is_a_frozen_copy(batch):
    from spoil_torchrl.modules import make_discriminator
    from spoil_torchrl.objectives import PUDiscriminatorLoss

    loss = PUDiscriminatorLoss(make_discriminator(5, 2, hidden_cells=(8,)))
    frozen = loss.log_ratio_module()
    before = frozen(batch["unlabeled"].clone())["log_ratio_performant"]
    with torch.no_grad():
        for p in loss.parameters():
            p.add_(1.0)  # the discriminator trains on
    torch.testing.assert_close(frozen(batch["unlabeled"].clone())["log_ratio_performant"], before)


def test_second_pass_boundaries():
    """Tests written against the survivors of the second mutation run."""
    from spoil_torchrl.modules import make_actor, make_discriminator
    from spoil_torchrl.objectives import DWBCLoss, PUDiscriminatorLoss, per_step_cost_limit

    dwbc_disc = make_discriminator(5, 2, hidden_cells=(8,), extra_inputs={"policy_log_prob": 1})
    with pytest.raises(ValueError, match="eta must lie in"):
        DWBCLoss(make_actor(5, 2, hidden_cells=(8,)), dwbc_disc, eta=1.0, alpha=100.0)
    bound = 0.5 / (0.1 * 0.9) + 1.0
    DWBCLoss(make_actor(5, 2, hidden_cells=(8,)), dwbc_disc, alpha=bound)  # exactly at the bound: allowed
    with pytest.raises(ValueError, match=r"\(D \(1 - D\)\) - 1 would be negative"):
        DWBCLoss(make_actor(5, 2, hidden_cells=(8,)), dwbc_disc, alpha=1.0)
    with pytest.raises(ValueError, match=r"\(D \(1 - D\)\) would be negative"):
        DWBCLoss(make_actor(5, 2, hidden_cells=(8,)), dwbc_disc, alpha=1.0, reference_offsets=False)
    with pytest.raises(ValueError, match="gamma"):
        per_step_cost_limit(1.0, 10, 0.0)
    disc = make_discriminator(5, 2, hidden_cells=(8,))
    assert PUDiscriminatorLoss(disc, class_prior=0.3, reduction="mean").class_prior == 0.3
    assert PUDiscriminatorLoss(disc, unlabeled="safe").tensor_keys.unlabeled == "safe"
    frozen = PUDiscriminatorLoss(disc).frozen_network()
    assert not any(p.requires_grad for p in frozen.parameters())


def test_a_nu_penalty_of_exactly_one_is_applied(batch):
    from spoil_torchrl.objectives import SpoilDICELoss

    with_penalty = SpoilDICELoss(_linear_nu(3.0), gradient_penalty=1.0)(batch.clone())["loss_nu"]
    without = SpoilDICELoss(_linear_nu(3.0), gradient_penalty=0.0)(batch.clone())["loss_nu"]
    torch.testing.assert_close(with_penalty - without, torch.tensor(9.0), rtol=1e-4, atol=1e-4)


def test_dice_transitions_refuses_an_empty_role_or_no_initial_states():
    from spoil_torchrl.objectives.keys import dice_transitions

    def batch(n, n_init):
        role = TensorDict(
            {
                "observation": torch.randn(n, 3),
                "next": {"observation": torch.randn(n, 3), "terminated": torch.zeros(n, 1, dtype=torch.bool)},
            },
            [n],
        )
        return TensorDict(
            {"unlabeled": role, "init": TensorDict({"observation": torch.randn(n_init, 3)}, [n_init])}, []
        )

    keys = DICE_KEYS
    for n, n_init in ((0, 4), (4, 0)):
        with pytest.raises(ValueError, match="X needs at least one transition"):
            dice_transitions(batch(n, n_init), **keys)


def test_seed_defaults_are_zero():
    kwargs = dict(n_safe=4, performance=0.5, n_performant=4, safeness=0.25, n_unlabeled=7)
    assert all(
        torch.equal(controlled_mix(_pools(), **kwargs)[k], controlled_mix(_pools(), **kwargs, seed=0)[k])
        for k in ("safe", "performant", "unlabeled")
    )
    safe, unsafe = torch.arange(10), torch.arange(100, 120)
    assert torch.equal(corrupt(safe, unsafe, 0.3), corrupt(safe, unsafe, 0.3, seed=0))


def test_feasible_return_tolerates_round_off_relative_to_the_threshold():
    from spoil_torchrl.eval import feasible_return

    reward = torch.ones(2, dtype=torch.float64)
    # cumulative cost 25 + 1e-8: above 25 by less than 1e-9 * 25 relative round-off -> not a violation
    cost = torch.tensor([25.0, 1e-8 * 0.5], dtype=torch.float64)
    assert feasible_return(reward, cost, 25.0) == 2.0
    cost = torch.tensor([25.0, 1e-7], dtype=torch.float64)  # beyond the round-off: the second step violates
    assert feasible_return(reward, cost, 25.0) == 1.0


def test_one_step_episodes_have_a_two_dimensional_mask():
    td = TensorDict(
        {
            "next": {"reward": torch.ones(2, 1), "cost": torch.zeros(2, 1)},
            "mask": torch.ones(2, 1, dtype=torch.bool),
        },
        [2, 1],
    )
    assert episode_metrics(td, cost_threshold=1.0)["length"].tolist() == [1, 1]


def test_feasible_return_round_off_edges():
    from spoil_torchrl.eval import feasible_return
    from spoil_torchrl.eval.metrics import ROUND_OFF

    reward = torch.ones(1, dtype=torch.float64)
    edge = 25.0 + ROUND_OFF * 25.0  # exactly at the tolerance: not a violation
    assert feasible_return(reward, torch.tensor([edge], dtype=torch.float64), 25.0) == 1.0
    # below a threshold of 1.5 the tolerance is 1.5e-9 (relative), not 2e-9
    cost = torch.tensor([1.5 + 1.7e-9], dtype=torch.float64)
    assert feasible_return(reward, cost, 1.5) == 0.0


def test_sums_and_means_are_taken_in_double_precision():
    from spoil_torchrl.eval import episode_cost, episode_return

    # in float32, 1e8 + 1 rounds to 1e8: a float32 sum of these steps would be 0
    steps = torch.tensor([1e8, 1.0, -1e8], dtype=torch.float32)
    assert episode_return(steps) == 1.0 and episode_cost(steps.abs() - torch.tensor([0.0, 0.0, 2e8])) == 1.0
    assert mean_of_last(steps, last=3) == pytest.approx(1.0 / 3.0)


def test_dice_transitions_keeps_a_two_dimensional_batch_shape():
    from spoil_torchrl.objectives.keys import dice_transitions

    role = TensorDict(
        {
            "observation": torch.randn(2, 3, 4),
            "next": {
                "observation": torch.randn(2, 3, 4),
                "terminated": torch.zeros(2, 3, 1, dtype=torch.bool),
            },
        },
        [2, 3],
    )
    batch = TensorDict({"unlabeled": role, "init": TensorDict({"observation": torch.randn(5, 4)}, [5])}, [])
    out = dice_transitions(batch, **DICE_KEYS)
    assert out.batch_shape == torch.Size([2, 3]) and out.current["observation"].shape == (6, 4)
