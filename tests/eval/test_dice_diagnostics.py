"""DICE diagnostics on hand-made batches whose answers are known."""

from __future__ import annotations

import json
import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn

from spoil_torchrl.eval.dice_diagnostics import (
    dice_diagnostics,
    source_masks,
    subsample,
    summary_scalars,
    support_accuracy,
    variance_shares,
    weight_shares,
)
from spoil_torchrl.eval.dice_explain import explain, explain_run
from spoil_torchrl.objectives import DemoDICELoss, SpoilDICELoss


class Linear1(nn.Module):
    """nu(s) = s[0] (a known, hand-set value function)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x[..., :1]


def _nu() -> TensorDictModule:
    return TensorDictModule(Linear1(), in_keys=["observation"], out_keys=["nu"])


def _batch() -> TensorDict:
    # 4 episodes of 2 steps: episode 0, 1 from source "a", 2, 3 from "b"; cost on odd steps of episode 2.
    obs = torch.tensor([[0.0], [1.0], [2.0], [3.0], [0.0], [1.0], [2.0], [3.0]])
    return TensorDict(
        {
            "observation": obs,
            "episode": torch.tensor([0, 0, 1, 1, 2, 2, 3, 3]),
            "next": {
                "observation": obs + 1.0,
                "terminated": torch.zeros(8, 1, dtype=torch.bool),
                "cost": torch.tensor([0, 0, 0, 0, 0, 1, 0, 0.0]).unsqueeze(-1),
            },
            "log_ratio_performant": torch.tensor([0.0, 1, 0, 1, 2, 2, 0, 0]).unsqueeze(-1),
            "safe_support": torch.tensor([1.0, 1, 1, 1, 0, 1, 0, 1]).unsqueeze(-1),
        },
        [8],
    )


def test_variance_shares_sum_to_one_and_name_the_varying_term():
    a = torch.randn(1000)
    shares = variance_shares(a + 3.0, {"a": a, "constant": torch.full((1000,), 2.0)})
    assert shares == pytest.approx({"a": 1.0, "constant": 0.0}, abs=1e-9)
    assert variance_shares(torch.ones(5), {"x": torch.randn(5)}) == {"x": 0.0}


def test_weight_shares_and_support_accuracy_by_hand():
    w = torch.tensor([1.0, 1.0, 2.0, 0.0])
    masks = {"x": torch.tensor([True, False, True, False])}
    assert weight_shares(w, masks) == {"x": {"weight": 0.75, "transitions": 0.5}}
    acc = support_accuracy(torch.tensor([1.0, 0, 1, 1]), torch.tensor([0.0, 2, 1, 0]), masks)
    assert acc["kept"] == 0.75
    assert acc["costly_among_kept"] == pytest.approx(1 / 3)
    assert acc["costly_kept"] == 0.5
    assert acc["kept_by_group"] == {"x": 1.0}


def test_spoildice_diagnostics_on_a_hand_set_nu():
    batch = _batch()
    gamma, lam = 0.5, 2.0
    loss = SpoilDICELoss(_nu(), gamma=gamma, gradient_penalty=0.0, init_lagrange=lam)
    init = TensorDict({"observation": torch.zeros(2, 1)}, [2])
    diag = dice_diagnostics(loss, batch, init, role="unlabeled", pools={"a": torch.tensor([0, 1])})
    s = batch["observation"].reshape(-1)
    bellman = gamma * (s + 1) - s  # = 0.5 - 0.5 s
    log_ratio = batch["log_ratio_performant"].reshape(-1)
    lam_support = lam * batch["safe_support"].reshape(-1)
    advantage = log_ratio + lam_support + bellman
    assert diag["spread"]["nu"] == pytest.approx(float(s.std(unbiased=False)))
    assert diag["spread"]["bellman"] == pytest.approx(float(bellman.std(unbiased=False)))
    assert diag["spread"]["lagrange_support"] == pytest.approx(float(lam_support.std(unbiased=False)))
    var = advantage.var(unbiased=False)
    for name, term in (
        ("bellman", bellman),
        ("log_ratio_performant", log_ratio),
        ("lagrange_support", lam_support),
    ):
        expected = float(((term - term.mean()) * (advantage - advantage.mean())).mean() / var)
        assert diag["variance_share"][name] == pytest.approx(expected, abs=1e-6)
    assert diag["variance_share"]["rest"] == pytest.approx(0.0, abs=1e-6)
    inside = batch["safe_support"].reshape(-1) > 0  # inside the support lambda * 1_S is constant
    a_in, b_in = advantage[inside], bellman[inside]
    expected_in = float(((b_in - b_in.mean()) * (a_in - a_in.mean())).mean() / a_in.var(unbiased=False))
    assert diag["variance_share_in_support"]["bellman"] == pytest.approx(expected_in, abs=1e-6)
    assert sum(diag["variance_share_in_support"].values()) == pytest.approx(1.0, abs=1e-6)
    w = torch.exp(advantage - 1)
    w = w / w.sum()
    assert diag["weight_share"]["a"]["weight"] == pytest.approx(float(w[:4].sum()), rel=1e-5)
    assert diag["weight_share"]["a"]["transitions"] == 0.5
    assert diag["weight_share"]["cost>0"]["weight"] == pytest.approx(float(w[5]), rel=1e-5)
    assert diag["support"]["costly_among_kept"] == pytest.approx(1 / 6)
    assert diag["support"]["kept_by_group"]["a"] == 1.0
    assert diag["lagrange"] == lam
    assert "unlabeled" not in batch.keys() and "dice_weight" not in batch.keys()  # the input is not modified
    scalars = summary_scalars(diag)
    assert scalars["dice/weight_on_cost"] == diag["weight_share"]["cost>0"]["weight"]
    text = explain(diag, {"kept": 0.4})
    assert "It keeps 40 % of D_P" in text and "sits on transitions with true cost > 0" in text
    assert "Inside the estimated support" in text and "nearly flat" not in text  # bellman spread 0.5


def test_diagnostics_of_a_dice_baseline_split_reward_and_bellman():
    batch = _batch()
    batch["reward"] = torch.zeros(8, 1)  # a flat reward: all variance comes from the Bellman term
    loss = DemoDICELoss(
        _nu(), alpha=0.1, gamma=0.5, gradient_penalty=0.0, regularization="safe", reward="reward"
    )
    init = TensorDict({"observation": torch.zeros(2, 1)}, [2])
    diag = dice_diagnostics(loss, batch, init, role="safe")
    assert diag["variance_share"]["bellman"] == pytest.approx(1.0)
    assert diag["variance_share"]["reward"] == pytest.approx(0.0, abs=1e-9)
    assert "lagrange" not in diag
    assert "nearly flat" not in explain(diag)


def test_explain_flags_a_flat_nu_and_explain_run_reads_results(tmp_path):
    diag = {
        "role": "unlabeled",
        "spread": {"nu": 0.0, "bellman": 0.0, "advantage": 1.0},
        "variance_share": {"bellman": 0.0, "reward": 1.0},
        "weight_share": {
            "cost>0": {"weight": 0.31, "transitions": 0.2},
            "unsafe-high": {"weight": 0.31, "transitions": 0.1},
        },
        "effective_sample_size": 0.5,
    }
    text = explain(diag)
    assert "nearly flat" in text and "favour costly" in text and "unsafe-high 31 %" in text
    even = {**diag, "weight_share": {"cost>0": {"weight": 0.2, "transitions": 0.205}}}
    assert "neither favour nor avoid" in explain(even)
    (tmp_path / "results.json").write_text(json.dumps({"algo": "spoildice", "dice_diagnostics": diag}))
    assert explain_run(tmp_path) == text
    (tmp_path / "results.json").write_text(json.dumps({"algo": "bc"}))
    with pytest.raises(ValueError, match="not a DICE method"):
        explain_run(tmp_path)
    with pytest.raises(FileNotFoundError):
        explain_run(tmp_path / "missing")


def test_subsample_and_source_masks():
    data = TensorDict({"x": torch.arange(100)}, [100])
    a, b = subsample(data, 10, seed=3), subsample(data, 10, seed=3)
    assert torch.equal(a["x"], b["x"]) and a.shape[0] == 10 and bool((a["x"].diff() > 0).all())
    assert subsample(data, 1000).shape[0] == 100
    masks = source_masks(torch.tensor([0, 1, 2]), {"p": [1, 2]})
    assert masks["p"].tolist() == [False, True, True]
    assert not math.isnan(weight_shares(torch.zeros(3), masks)["p"]["weight"])


def test_diagnostics_leave_the_global_random_stream_alone():
    from spoil_torchrl.modules import make_value_network

    batch = _batch()
    loss = SpoilDICELoss(make_value_network(1, hidden_cells=(4,)), gradient_penalty=1.0)  # the penalty draws
    init = TensorDict({"observation": torch.zeros(2, 1)}, [2])
    torch.manual_seed(0)
    expected = torch.rand(3)
    torch.manual_seed(0)
    dice_diagnostics(loss, batch, init, role="unlabeled")
    assert torch.equal(torch.rand(3), expected)


def test_several_constraints_report_each_cut_against_each_constraints_cost():
    """With two cuts, the support is their intersection and each cut is set against each constraint's own cost
    (rows: cuts, columns: constraints; the off-diagonal entries differ, so a transposed table fails)."""
    batch = _batch()
    a_cut = torch.tensor([1.0, 1, 1, 1, 0, 1, 0, 1]).unsqueeze(-1)
    b_cut = torch.tensor([1.0, 1, 1, 0, 1, 1, 0, 1]).unsqueeze(-1)
    batch["safe_support_a"], batch["safe_support_b"] = a_cut, b_cut
    batch["safe_support"] = torch.cat([a_cut, b_cut], -1)
    costs = {
        "a": torch.tensor([0.0, 0, 0, 0, 1, 0, 1, 1]).unsqueeze(-1),  # cut a keeps step 7, cut b steps 4, 7
        "b": torch.tensor([0.0, 0, 0, 1, 0, 1, 0, 0]).unsqueeze(-1),  # cut a keeps both, cut b step 5
    }
    batch["next", "constraint_costs"] = TensorDict(costs, [8])
    init = TensorDict({"observation": torch.zeros(2, 1)}, [2])
    loss = SpoilDICELoss(_nu(), gamma=0.5, gradient_penalty=0.0, constraints=2)
    diag = dice_diagnostics(loss, batch, init, role="unlabeled")
    by = diag["support"]["by_constraint"]
    assert by["costly"] == {"a": 3 / 8, "b": 2 / 8}
    assert by["costly_kept"] == {
        "a": {"a": 1 / 3, "b": 1.0},
        "b": {"a": 2 / 3, "b": 0.5},
        "all": {"a": 1 / 3, "b": 0.5},
    }
    assert diag["support"]["kept"] == 5 / 8  # the intersection: steps 0, 1, 2, 5, 7
    text = explain(diag)
    assert "the a cut lets in 33 % / 100 %, the b cut 67 % / 50 %, their intersection 33 % / 50 %" in text

    merged = batch.exclude("safe_support_a", "safe_support_b")  # one support for both constraints
    merged["safe_support"] = a_cut * b_cut
    diag = dice_diagnostics(
        SpoilDICELoss(_nu(), gamma=0.5, gradient_penalty=0.0), merged, init, role="unlabeled"
    )
    assert diag["support"]["by_constraint"]["costly_kept"] == {"all": {"a": 1 / 3, "b": 0.5}}
    assert "the support lets in 33 % / 50 %" in explain(diag)

    batch["next", "constraint_costs", "b"] = torch.zeros(8, 1)  # nothing costly on b: no share to report
    diag = dice_diagnostics(loss, batch, init, role="unlabeled")
    assert diag["support"]["by_constraint"]["costly"]["b"] == 0.0
    assert "the a cut lets in 33 % / -, the b cut 67 % / -" in explain(diag)

    named_all = batch.exclude("safe_support_b").set("safe_support_all", b_cut)
    with pytest.raises(ValueError, match="'all'"):
        dice_diagnostics(loss, named_all, init, role="unlabeled")

    del batch["next", "constraint_costs"]  # no per-constraint costs: nothing to set the support against
    assert "by_constraint" not in dice_diagnostics(loss, batch, init, role="unlabeled")["support"]
