"""The compiled update step: the eager step's numbers within float tolerance, the same random stream, and a
clean (logged) fall-back to the eager step."""

from __future__ import annotations

import logging

import pytest
import torch

from spoil_torchrl.modules import make_actor, make_discriminator, make_value_network
from spoil_torchrl.objectives import (
    COptiDICELoss,
    DemoDICELoss,
    DWBCLoss,
    PUDiscriminatorLoss,
    SafeDICELoss,
    SpoilDICELoss,
    WeightedBCLoss,
)
from spoil_torchrl.trainers import CompiledStepper, MultiLossStepper, StepEvery
from spoil_torchrl.trainers.compiled import use_fused_adam
from spoil_torchrl.trainers.precision import (
    REDUCED_PRECISION_ERROR,
    matmul_precision,
    matmul_relative_error,
)
from tests.conftest import ACT_DIM, OBS_DIM, dual_batch

STEPS = 4


def _sgd(params, lr: float = 1e-2) -> torch.optim.Optimizer:
    """The tests' optimiser. Not Adam: nu's constant offset is free in every DICE dual, so the gradient of nu's
    output bias is 0 up to float noise, which Adam's first steps scale to +/- lr whatever its size; any two
    correct implementations (or machines) then differ by lr in that bias. SGD keeps float noise as small as it
    is, so a few steps of two implementations can be compared to a tight tolerance."""
    return torch.optim.SGD(list(params), lr=lr)


def _spoildice(distribution: str, penalty: float, cells: tuple[int, ...] = (32, 32)):
    """SpoilDICE + weighted BC on its weights: the same initial weights on every call."""
    torch.manual_seed(3)
    dice = SpoilDICELoss(make_value_network(OBS_DIM, hidden_cells=cells), gradient_penalty=penalty)
    actor = WeightedBCLoss(
        make_actor(OBS_DIM, ACT_DIM, hidden_cells=cells, distribution=distribution),
        role="unlabeled",
        weight="dice_weight",
    )
    optimizers = [
        _sgd(dice.nu_network_params.values(True, True)),
        _sgd([dice.lagrange]),
        _sgd(actor.parameters()),
    ]
    return {"dice": dice, "actor": actor}, optimizers


def _demodice_s():
    """DemoDICE-S's main stage: nu on D_S with the reward log d_P/d_S, weighted BC on D_S."""
    torch.manual_seed(3)
    dice = DemoDICELoss(
        make_value_network(OBS_DIM, hidden_cells=(32, 32)),
        gradient_penalty=10.0,
        regularization="safe",
        reward="log_ratio_performant",
    )
    actor = WeightedBCLoss(
        make_actor(OBS_DIM, ACT_DIM, hidden_cells=(32,)), role="safe", weight="dice_weight"
    )
    optimizers = [_sgd(dice.nu_network_params.values(True, True)), _sgd(actor.parameters())]
    return {"dice": dice, "actor": actor}, optimizers


def _discriminators():
    """Stage 1: C_P (gradient penalty 10) and C_S (none) against D_U, as the recipe pre-trains them."""
    torch.manual_seed(3)
    losses = {
        f"disc_{role}": PUDiscriminatorLoss(
            make_discriminator(OBS_DIM, ACT_DIM, hidden_cells=(32, 32)),
            positive=role,
            gradient_penalty=penalty,
        )
        for role, penalty in (("performant", 10.0), ("safe", 0.0))
    }
    return losses, [_sgd(loss.parameters()) for loss in losses.values()]


def _safedice():
    """SafeDICE's main stage (its logit read from an entry dual_batch has), weighted BC on D_U."""
    torch.manual_seed(3)
    dice = SafeDICELoss(make_value_network(OBS_DIM, hidden_cells=(32, 32)), alpha=0.5, gradient_penalty=10.0)
    dice.set_keys(logit="log_ratio_performant")
    actor = WeightedBCLoss(
        make_actor(OBS_DIM, ACT_DIM, hidden_cells=(32,)), role="unlabeled", weight="dice_weight"
    )
    optimizers = [_sgd(dice.nu_network_params.values(True, True)), _sgd(actor.parameters())]
    return {"dice": dice, "actor": actor}, optimizers


def _dwbc():
    """DWBC: the policy and D(s, a, log pi) trained jointly, the discriminator's optimiser every 2nd step."""
    torch.manual_seed(3)
    loss = DWBCLoss(
        make_actor(OBS_DIM, ACT_DIM, hidden_cells=(32,)),
        make_discriminator(OBS_DIM, ACT_DIM, hidden_cells=(32,), extra_inputs={"policy_log_prob": 1}),
        alpha=7.5,
        eta=0.5,
    )
    optimizers = [
        _sgd(loss.actor_network_params.values(True, True)),
        StepEvery(_sgd(loss.discriminator_network_params.values(True, True)), 2),
    ]
    return {"dwbc": loss}, optimizers


def _coptidice(cost_ub_epsilon: float):
    """COptiDICE's main stage (nu, chi, tau, lambda; chi off with cost_ub_epsilon=0), weighted BC on D_U."""
    torch.manual_seed(3)
    dice = COptiDICELoss(
        make_value_network(OBS_DIM, hidden_cells=(32,)),
        make_value_network(OBS_DIM, hidden_cells=(32,)),
        cost_limit=0.2,
        cost_ub_epsilon=cost_ub_epsilon,
        gradient_penalty=10.0,
    )
    actor = WeightedBCLoss(
        make_actor(OBS_DIM, ACT_DIM, hidden_cells=(32,)), role="unlabeled", weight="dice_weight"
    )
    return {"dice": dice, "actor": actor}, [_sgd(dice.parameters()), _sgd(actor.parameters())]


def _filtered_bc():
    """Weighted BC with its weight read from the batch (filtered BC's ``safe_support`` on D_P)."""
    torch.manual_seed(3)
    actor = WeightedBCLoss(
        make_actor(OBS_DIM, ACT_DIM, hidden_cells=(32,)), role="performant", weight="safe_support"
    )
    return {"actor": actor}, [_sgd(actor.parameters())]


def _run(stepper, batches):
    """``STEPS`` steps from a fixed random stream; the outputs, the parameters and the stream's state after."""
    torch.manual_seed(11)
    outputs = [stepper.step(None, batch.clone()) for batch in batches]
    return outputs, _parameters(stepper.losses), torch.get_rng_state()


@pytest.fixture(scope="module")
def batches():
    torch.manual_seed(5)
    return [dual_batch(n_unl=64, n_init=16) for _ in range(STEPS)]


@pytest.mark.parametrize(
    "build",
    [
        pytest.param(lambda: _spoildice("normal", 1e-4), id="spoildice-normal-penalty"),
        pytest.param(lambda: _spoildice("tanh_normal", 10.0), id="spoildice-tanh-penalty10"),
        pytest.param(lambda: _spoildice("normal", 0.0), id="spoildice-no-penalty"),
        pytest.param(_demodice_s, id="demodice-s"),
        pytest.param(_safedice, id="safedice"),
        pytest.param(lambda: _coptidice(0.01), id="coptidice"),
        pytest.param(lambda: _coptidice(0.0), id="coptidice-no-chi"),
        pytest.param(_filtered_bc, id="filtered-bc"),
        pytest.param(_dwbc, id="dwbc"),
        pytest.param(_discriminators, id="discriminators"),
    ],
)
def test_compiled_steps_match_eager_steps(build, batches):
    eager_out, eager_params, eager_rng = _run(MultiLossStepper(*build()), batches)
    compiled = CompiledStepper(*build())
    out, params, rng = _run(compiled, batches)
    assert compiled.compiled, "the step fell back to eager"
    assert torch.equal(rng, eager_rng)  # the penalty's random points: the same draws, in the same order
    for a, b in zip(eager_out, out, strict=True):
        assert sorted(a.keys()) == sorted(b.keys())
        for key in a.keys():
            torch.testing.assert_close(
                b[key], a[key], rtol=1e-4, atol=1e-5, msg=lambda m, key=key: f"{key}: {m}"
            )
    initial = _parameters(build()[0])
    for key, value in eager_params.items():
        torch.testing.assert_close(
            params[key], value, rtol=1e-4, atol=1e-5, msg=lambda m, key=key: f"{key}: {m}"
        )
    assert any(not torch.equal(value, initial[key]) for key, value in eager_params.items()), "nothing moved"


def _parameters(losses) -> dict[str, torch.Tensor]:
    return {
        f"{name}.{key}": p.detach().clone()
        for name, loss in losses.items()
        for key, p in loss.named_parameters()
    }


def _adam(losses, optimizers):
    """The same losses with the recipe's optimiser, Adam."""
    return losses, [torch.optim.Adam(o.param_groups[0]["params"], lr=1e-3) for o in optimizers]


def test_compiled_steps_are_deterministic(batches):
    stepper = CompiledStepper(*_adam(*_spoildice("normal", 1e-4)))
    assert not any(g["fused"] for o in stepper.optimizers for g in o.param_groups)  # not before it compiles
    _, first, _ = _run(stepper, batches)
    assert all(g["fused"] for o in stepper.optimizers for g in o.param_groups)  # Adam: the fused kernel
    _, second, _ = _run(CompiledStepper(*_adam(*_spoildice("normal", 1e-4))), batches)
    for key, value in first.items():
        assert torch.equal(second[key], value), key


def test_a_loss_without_compiled_form_runs_eagerly_and_says_so(caplog, batches):
    class UsersOwnBC(WeightedBCLoss):
        """A user's subclass: the compiled forms are registered by exact class, so it has none."""

    def build():
        torch.manual_seed(3)
        loss = UsersOwnBC(make_actor(OBS_DIM, ACT_DIM, hidden_cells=(16,)), role="performant")
        return {"actor": loss}, [torch.optim.Adam(loss.parameters(), lr=1e-3)]

    with caplog.at_level(logging.WARNING, logger="spoil_torchrl.trainers.compiled"):
        stepper = CompiledStepper(*build())
    assert "UsersOwnBC has no compiled form; the update step runs eagerly" in caplog.text
    _, eager_params, _ = _run(MultiLossStepper(*build()), batches)
    _, params, _ = _run(stepper, batches)
    assert not stepper.compiled and not stepper.optimizers[0].param_groups[0]["fused"]
    for key, value in eager_params.items():
        assert torch.equal(params[key], value), key


def test_a_step_that_fails_to_compile_runs_eagerly_from_the_same_random_state(caplog, monkeypatch, batches):
    def broken_compile(fn, **kwargs):
        def fails(*args):
            raise RuntimeError("no C++ compiler found\nsecond line")

        return fails

    _, eager_params, eager_rng = _run(MultiLossStepper(*_spoildice("normal", 1e-4)), batches)
    monkeypatch.setattr(torch, "compile", broken_compile)
    stepper = CompiledStepper(*_spoildice("normal", 1e-4))
    with caplog.at_level(logging.WARNING, logger="spoil_torchrl.trainers.compiled"):
        _, params, rng = _run(stepper, batches)
    assert not stepper.compiled
    assert caplog.text.count("did not compile (RuntimeError: no C++ compiler found); it runs eagerly") == 1
    assert torch.equal(rng, eager_rng)
    for key, value in eager_params.items():
        assert torch.equal(params[key], value), key


def test_compiled_stepper_keeps_the_eager_state_dict():
    losses, optimizers = _spoildice("normal", 1e-4)
    eager = MultiLossStepper(losses, optimizers)
    compiled = CompiledStepper.from_stepper(eager)
    assert compiled.losses == eager.losses and compiled.optimizers == eager.optimizers
    assert compiled.state_dict().keys() == eager.state_dict().keys()


def test_more_steppers_than_dynamos_recompile_limit_all_compile():
    """Dynamo recompiles one code object at most 8 times; every stepper has its own, so a process (a notebook,
    this test suite) can build any number."""
    steppers = []
    for i in range(9):  # named apart: no two steppers can share a compiled graph
        loss = _filtered_bc()[0]["actor"]
        steppers.append(CompiledStepper({f"actor_{i}": loss}, [_sgd(loss.parameters())]))
    batch = dual_batch()
    for stepper in steppers:
        stepper.step(None, batch.clone())
    assert all(stepper.compiled for stepper in steppers)


def test_compiled_steps_with_medium_matmul_precision_match_ieee_eager_steps(batches):
    """``train.matmul_precision=medium`` (the default preset's) hands float32 products to oneDNN. Where oneDNN
    keeps float32 kernels (AVX-512 CPUs without AMX, this project's) four steps stay within 1e-3 of IEEE eager
    steps; true bfloat16 arithmetic (autocast) drifts by 0.26 relative in the same four steps. (PyTorch hands
    products as large as the paper's 256-cell layers to oneDNN, not the 32-cell ones of the other tests.)"""
    with matmul_precision("medium"):
        if matmul_relative_error() > REDUCED_PRECISION_ERROR:
            pytest.skip(
                "this CPU's oneDNN computes float32 products in bfloat16 at medium (the recipe warns)"
            )
    eager_out, eager_params, _ = _run(MultiLossStepper(*_spoildice("normal", 10.0, (256, 256))), batches)
    compiled = CompiledStepper(*_spoildice("normal", 10.0, (256, 256)))
    with matmul_precision("medium"):
        out, params, _ = _run(compiled, batches)
    assert compiled.compiled and torch.get_float32_matmul_precision() == "highest"
    for a, b in zip(eager_out, out, strict=True):
        for key in a.keys():
            torch.testing.assert_close(b[key], a[key], rtol=1e-3, atol=1e-4, msg=lambda m, k=key: f"{k}: {m}")
    for key, value in eager_params.items():
        torch.testing.assert_close(params[key], value, rtol=1e-3, atol=1e-4, msg=lambda m, k=key: f"{k}: {m}")


def test_matmul_precision_is_scoped_and_checked():
    with pytest.raises(RuntimeError, match="inside"), matmul_precision("medium"):
        assert torch.get_float32_matmul_precision() == "medium"
        raise RuntimeError("inside")
    assert torch.get_float32_matmul_precision() == "highest"
    with pytest.raises(ValueError, match="one of \\('highest', 'high', 'medium'\\), got 'bf16'"):
        with matmul_precision("bf16"):
            pass


def test_use_fused_adam_reaches_wrapped_adam_and_leaves_other_optimizers():
    dwbc, optimizers = _adam(*_dwbc())
    optimizers[1] = StepEvery(optimizers[1], 2)
    sgd = _sgd(dwbc["dwbc"].parameters())
    use_fused_adam([*optimizers, sgd])
    assert optimizers[0].param_groups[0]["fused"] and optimizers[1].optimizer.param_groups[0]["fused"]
    assert "fused" not in sgd.param_groups[0] or not sgd.param_groups[0]["fused"]
