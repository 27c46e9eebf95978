"""The gradient penalty's two forms (``DICELoss.penalty_form``): the ReLU chain written out gives autograd's
values and gradients to float rounding, with fewer products, for every DICE loss, eager and compiled; networks
that are not a plain ReLU chain are refused for it."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from torch import nn

from spoil_torchrl.modules import make_value_network
from spoil_torchrl.objectives import SpoilDICELoss
from spoil_torchrl.objectives.input_gradient import relu_chain_layers, values_and_input_gradient
from spoil_torchrl.trainers.compiled import detached, pure_losses, step_inputs, update_gradients
from tests.conftest import OBS_DIM, dual_batch
from tests.objectives.test_contract import CASES, assert_compiles_whole

DICE = ["spoildice", "spoildice_two_constraints", "demodice", "safedice", "coptidice"]


def _update(loss, batch, form: str):
    """The update's gradients and outputs of ``loss`` under ``form``, from the same random draws."""
    loss.penalty_form = form
    losses = {"loss": loss}
    torch.manual_seed(7)
    inputs = step_inputs(losses, pure_losses(losses), batch.clone())
    grads, (total, outputs) = update_gradients(losses)(detached({"loss": loss.term_parameters()}), inputs)
    return grads["loss"], total, outputs


@pytest.mark.parametrize("name", DICE)
def test_the_relu_chain_gives_autograds_losses_and_gradients(name):
    case = CASES[name]
    loss, batch = case.make(), case.batch()
    grads, total, outputs = _update(loss, batch, "autograd")
    chain_grads, chain_total, chain_outputs = _update(loss, batch, "relu_chain")
    torch.testing.assert_close(chain_total, total)
    for key in outputs:
        torch.testing.assert_close(chain_outputs[key], outputs[key], msg=lambda m, key=key: f"{key}: {m}")
    moved = 0
    for key, expected in grads.items():
        torch.testing.assert_close(chain_grads[key], expected, msg=lambda m, key=key: f"{key}: {m}")
        moved += bool(expected.abs().sum() > 0) and key.startswith("nu.") and key.endswith("weight")
    assert moved == 3, "nu's weights got no gradient"


@pytest.mark.compiles
@pytest.mark.parametrize("name", ["spoildice", "coptidice"])
def test_the_relu_chain_compiles_whole_and_gives_the_eager_gradients(name):
    case = CASES[name]
    loss = case.make()
    loss.penalty_form = "relu_chain"
    assert_compiles_whole(loss, case.batch())


def test_the_relu_chain_does_fewer_products_than_autograd():
    """Counted with PyTorch's FLOP formulas, at the bench's sizes: autograd's second derivative sends zeros back
    through the forward pass of every penalty point (docs/speed.md); the written-out chain does not."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    from bench_losses import make_batch
    from flops import count_flops

    loss = SpoilDICELoss(make_value_network(28, hidden_cells=(256, 256)), gamma=0.99, gradient_penalty=10.0)
    batch = make_batch(512, 512, 28, 2)
    flops = {}
    for form in ("autograd", "relu_chain"):
        flops[form] = count_flops(lambda form=form: _update(loss, batch, form))
    # nu's products: autograd 1.71 GFLOP, the chain 1.42 (the penalty's points: 1,536 rows, 512 of them s)
    assert flops["relu_chain"] < 0.86 * flops["autograd"], flops


def test_values_and_input_gradient_agree_on_a_chain_and_refuse_what_is_not_one():
    net = nn.Sequential(nn.Linear(OBS_DIM, 16), nn.ReLU(), nn.Linear(16, 16), nn.ReLU(), nn.Linear(16, 1))
    params = dict(net.named_parameters())

    def call(p, s):
        return torch.func.functional_call(net, p, (s,))

    states = torch.randn(12, OBS_DIM)
    layers = relu_chain_layers(net)
    assert layers == ["0", "2", "4"]
    g, v = values_and_input_gradient(call, params, states, layers=layers, value_rows=5)
    expected = torch.func.vmap(torch.func.grad(lambda s: call(params, s[None]).sum()))(states)
    torch.testing.assert_close(g, expected)
    torch.testing.assert_close(v, net(states[:5]).squeeze(-1))
    for other in (
        nn.Sequential(nn.Linear(OBS_DIM, 16), nn.Tanh(), nn.Linear(16, 1)),
        nn.Sequential(nn.Linear(OBS_DIM, 16), nn.ReLU(), nn.Linear(16, 2)),
        nn.Sequential(nn.Linear(OBS_DIM, 16, bias=False), nn.ReLU(), nn.Linear(16, 1)),
        nn.Sequential(nn.Linear(OBS_DIM, 16), nn.ReLU()),
        nn.Linear(OBS_DIM, 1),
    ):
        assert relu_chain_layers(other) is None


def test_a_network_that_is_no_relu_chain_is_refused_for_it_and_bad_forms_are_named():
    from tensordict.nn import TensorDictModule
    from torchrl.modules import MLP

    tanh = TensorDictModule(
        MLP(in_features=OBS_DIM, out_features=1, num_cells=[16], activation_class=nn.Tanh),
        in_keys=["observation"],
        out_keys=["nu"],
    )
    loss = SpoilDICELoss(tanh)
    with pytest.raises(ValueError, match="plain Linear/ReLU chain"):
        loss.penalty_form = "relu_chain"
    assert loss.penalty_form == "autograd"
    with pytest.raises(ValueError, match="penalty_form must be one of"):
        loss.penalty_form = "fast"
    loss(dual_batch())  # still usable, in autograd's form


def test_a_run_gives_its_dice_losses_the_configured_form_and_a_run_without_it_reads_as_autograd():
    from types import SimpleNamespace

    from omegaconf import OmegaConf

    from spoil_torchrl.modules import make_actor
    from spoil_torchrl.objectives import WeightedBCLoss
    from spoil_torchrl.runs.resume import settings_differ
    from spoil_torchrl.runs.training import use_penalty_form

    dice = SpoilDICELoss(make_value_network(OBS_DIM, hidden_cells=(16,)))
    stepper = SimpleNamespace(losses={"dice": dice, "actor": WeightedBCLoss(make_actor(OBS_DIM, 2))})
    use_penalty_form(stepper, OmegaConf.create({"steps": 10, "penalty_form": "relu_chain"}))
    assert dice.penalty_form == "relu_chain" and dice.penalty_layers("nu_network") == ["0", "2"]
    use_penalty_form(stepper, OmegaConf.create({"steps": 10}))
    assert dice.penalty_form == "autograd" and dice.penalty_layers("nu_network") is None
    old = "train:\n  steps: 10"
    assert settings_differ(old, "train:\n  steps: 10\n  penalty_form: autograd") == []
    assert settings_differ(old, "train:\n  steps: 10\n  penalty_form: relu_chain") == ["train.penalty_form"]
