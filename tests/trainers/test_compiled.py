"""The compiled step computes the eager step's numbers (losses, random gradient-penalty points, Adam)."""

from __future__ import annotations

import logging

import pytest
import torch
from tensordict import TensorDict

from spoil_torchrl.modules import make_actor, make_discriminator, make_value_network
from spoil_torchrl.objectives import PUDiscriminatorLoss, SpoilDICELoss, WeightedBCLoss
from spoil_torchrl.trainers import MultiLossStepper
from spoil_torchrl.trainers.compiled import CompiledStepper, compile_stepper
from tests.conftest import ACT_DIM, OBS_DIM, dual_batch


def _spoildice():
    torch.manual_seed(0)
    dice = SpoilDICELoss(make_value_network(OBS_DIM, hidden_cells=(32, 32)), gradient_penalty=1.0)
    bc = WeightedBCLoss(
        make_actor(OBS_DIM, ACT_DIM, hidden_cells=(32, 32)), role="unlabeled", weight="dice_weight"
    )
    optimizers = [torch.optim.Adam(dice.parameters(), lr=1e-2), torch.optim.Adam(bc.parameters(), lr=1e-2)]
    return MultiLossStepper({"dice": dice, "actor": bc}, optimizers)


def _discriminators():
    torch.manual_seed(0)
    losses = {
        role: PUDiscriminatorLoss(
            make_discriminator(OBS_DIM, ACT_DIM, hidden_cells=(32,)), positive=role, gradient_penalty=10.0
        )
        for role in ("performant", "safe")
    }
    return MultiLossStepper(
        losses, [torch.optim.Adam(loss.parameters(), lr=1e-2) for loss in losses.values()]
    )


def _run(stepper, batches):
    logs = []
    for k, batch in enumerate(batches):
        torch.manual_seed(100 + k)  # the same random draws (penalty points, permutations) in both runs
        logs.append(stepper.step(None, batch.clone()))
    return logs


@pytest.mark.parametrize("make", [_spoildice, _discriminators], ids=["spoildice+bc", "discriminators"])
def test_compiled_steps_match_eager_steps(make):
    torch.manual_seed(1)
    batches = [dual_batch() for _ in range(3)]
    eager, compiled = make(), CompiledStepper.from_stepper(make())
    eager_logs, compiled_logs = _run(eager, batches), _run(compiled, batches)
    assert compiled.eager_reason is None  # it really compiled
    for a, b in zip(eager_logs, compiled_logs, strict=True):
        assert a.keys() == b.keys()
        for key in a.keys():
            torch.testing.assert_close(a[key], b[key], rtol=1e-4, atol=1e-5, msg=key)
    for name, loss in eager.losses.items():
        theirs = dict(compiled.losses[name].named_parameters())
        for key, param in loss.named_parameters():
            torch.testing.assert_close(param, theirs[key], rtol=1e-4, atol=1e-5, msg=f"{name}.{key}")
    # the optimisers' state is the eager stepper's: a checkpoint of one loads into the other
    make().load_state_dict(compiled.state_dict())


def test_a_step_that_cannot_compile_trains_eagerly_and_says_so(caplog):
    stepper = CompiledStepper.from_stepper(_spoildice())

    def broken(*args):
        raise RuntimeError("no C++ compiler")

    stepper.compiled = broken
    with caplog.at_level(logging.WARNING):
        out = stepper.step(None, dual_batch())
    assert stepper.eager_reason == "RuntimeError: no C++ compiler"
    assert "could not be compiled (RuntimeError: no C++ compiler); training eagerly" in caplog.text
    assert "dice.loss_nu" in out.keys() and torch.isfinite(out["dice.loss_nu"])
    assert compile_stepper(stepper, False) is stepper


def test_batch_entries_written_by_one_loss_reach_the_next():
    stepper = CompiledStepper.from_stepper(_spoildice())
    batch = dual_batch()
    out = stepper.step(None, batch)
    assert 0.0 < float(out["actor.loss_actor"].abs()) and isinstance(out, TensorDict)


def test_compile_setting_must_be_a_boolean():
    from spoil_torchrl.trainers.settings import SettingsError, check_settings

    check_settings({"train": {"compile": True}})
    with pytest.raises(SettingsError, match=r"train.compile = 'yes': expected true or false"):
        check_settings({"train": {"compile": "yes"}})
