"""The compiled update step: the eager step's numbers within float tolerance, the same random stream, and a
clean (logged) fall-back to the eager step."""

from __future__ import annotations

import copy
import logging

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictSequential
from torchrl.objectives import LossModule

from spoil_torchrl.modules import make_actor
from spoil_torchrl.objectives import SpoilDICELoss, WeightedBCLoss
from spoil_torchrl.precision import (
    REDUCED_PRECISION_ERROR,
    matmul_precision,
    matmul_relative_error,
)
from spoil_torchrl.trainers import CompiledStepper, MultiLossStepper, StepEvery
from spoil_torchrl.trainers.fused_adam import use_fused_adam
from tests.conftest import ACT_DIM, OBS_DIM, dual_batch
from tests.trainers.steppers import (
    STEPS,
    adam,
    coptidice,
    demodice_s,
    discriminators,
    dwbc,
    filtered_bc,
    parameters_of,
    run,
    safedice,
    sgd,
    spoildice,
)

pytestmark = pytest.mark.compiles


@pytest.fixture(scope="module")
def batches():
    torch.manual_seed(5)
    return [dual_batch(n_unl=64, n_init=16) for _ in range(STEPS)]


@pytest.mark.parametrize(
    "build",
    [
        pytest.param(lambda: spoildice("normal", 1e-4), id="spoildice-normal-penalty"),
        pytest.param(lambda: spoildice("tanh_normal", 10.0), id="spoildice-tanh-penalty10"),
        pytest.param(lambda: spoildice("normal", 0.0), id="spoildice-no-penalty"),
        pytest.param(demodice_s, id="demodice-s"),
        pytest.param(safedice, id="safedice"),
        pytest.param(lambda: coptidice(0.01), id="coptidice"),
        pytest.param(lambda: coptidice(0.0), id="coptidice-no-chi"),
        pytest.param(filtered_bc, id="filtered-bc"),
        pytest.param(dwbc, id="dwbc"),
        pytest.param(discriminators, id="discriminators"),
    ],
)
def test_compiled_steps_match_eager_steps(build, batches):
    eager_out, eager_params, eager_rng = run(MultiLossStepper(*build()), batches)
    compiled = CompiledStepper(*build())
    out, params, rng = run(compiled, batches)
    assert compiled.compiled, "the step fell back to eager"
    assert torch.equal(rng, eager_rng)  # the penalty's random points: the same draws, in the same order
    for a, b in zip(eager_out, out, strict=True):
        assert sorted(a.keys()) == sorted(b.keys())
        for key in a.keys():
            torch.testing.assert_close(
                b[key], a[key], rtol=1e-4, atol=1e-5, msg=lambda m, key=key: f"{key}: {m}"
            )
    initial = parameters_of(build()[0])
    for key, value in eager_params.items():
        torch.testing.assert_close(
            params[key], value, rtol=1e-4, atol=1e-5, msg=lambda m, key=key: f"{key}: {m}"
        )
    assert any(not torch.equal(value, initial[key]) for key, value in eager_params.items()), "nothing moved"


def test_compiled_steps_are_deterministic(batches):
    stepper = CompiledStepper(*adam(*spoildice("normal", 1e-4)))
    assert not any(g["fused"] for o in stepper.optimizers for g in o.param_groups)  # not before it compiles
    _, first, _ = run(stepper, batches)
    assert all(g["fused"] for o in stepper.optimizers for g in o.param_groups)  # Adam: the fused kernel
    _, second, _ = run(CompiledStepper(*adam(*spoildice("normal", 1e-4))), batches)
    for key, value in first.items():
        assert torch.equal(second[key], value), key


def test_the_cpu_steps_cpp_wrapper_computes_the_python_wrappers_numbers_bit_for_bit(batches):
    """On a CPU the step is compiled with Inductor's C++ wrapper; ``mode="default"`` keeps the Python one.
    The kernels are the same, so every output and parameter is equal, not close."""
    cpp = CompiledStepper(*adam(*spoildice("normal", 1e-4)))
    python = CompiledStepper(*adam(*spoildice("normal", 1e-4)), mode="default")
    (cpp_out, cpp_params, _), (py_out, py_params, _) = run(cpp, batches), run(python, batches)
    assert cpp.compiled and python.compiled
    for a, b in zip(cpp_out, py_out, strict=True):
        assert all(torch.equal(a[key], b[key]) for key in a.keys())
    assert all(torch.equal(cpp_params[key], value) for key, value in py_params.items())


def test_a_compiled_stepper_loaded_mid_run_continues_as_the_run_it_was_loaded_from(batches):
    """The compiled step keeps its parameters from step to step: a state loaded after it compiled is the one it
    trains on (loading copies into the optimisers' parameters), step for step as the stepper it came from."""
    source = CompiledStepper(*adam(*spoildice("normal", 1e-4)))
    run(source, batches[:2])
    target = CompiledStepper(*adam(*spoildice("normal", 1e-4)))
    run(target, batches[3:])  # compiled, and one step away from its start: not the source's state
    target.load_state_dict(
        copy.deepcopy(source.state_dict())
    )  # as from a checkpoint: Adam's moments not shared
    _, expected, _ = run(source, batches[2:])
    _, got, _ = run(target, batches[2:])
    assert all(torch.equal(got[key], value) for key, value in expected.items())


def test_a_subclass_of_a_loss_compiles_and_trains_as_its_parent(batches):
    class UsersOwnSpoilDICE(SpoilDICELoss):
        """A user's subclass: the compiled step calls the methods it inherits."""

    def build(cls):
        losses, optimizers = spoildice("normal", 1e-4)
        dice = losses["dice"]
        own = cls(dice.nu_network, gradient_penalty=dice.gradient_penalty)
        own.load_state_dict(dice.state_dict())
        optimizers[0] = torch.optim.SGD(own.nu_network_params.values(True, True), lr=1e-2)
        optimizers[1] = torch.optim.SGD([own.lagrange], lr=1e-2)
        return {"dice": own, "actor": losses["actor"]}, optimizers

    stepper = CompiledStepper(*build(UsersOwnSpoilDICE))
    _, params, _ = run(stepper, batches)
    _, parent_params, _ = run(CompiledStepper(*build(SpoilDICELoss)), batches)
    assert stepper.compiled
    for key, value in parent_params.items():
        assert torch.equal(params[key], value), key


def _assert_trains_eagerly(build, batches, caplog, why: str) -> None:
    """A CompiledStepper of ``build()`` says ``why`` once and trains as the eager stepper, bit for bit."""
    with caplog.at_level(logging.WARNING, logger="spoil_torchrl.trainers.compiled"):
        stepper = CompiledStepper(*build())
    assert f"{why}; the update step runs eagerly" in caplog.text
    _, eager_params, _ = run(MultiLossStepper(*build()), batches)
    _, params, _ = run(stepper, batches)
    assert not stepper.compiled and not stepper.optimizers[0].param_groups[0]["fused"]
    for key, value in eager_params.items():
        assert torch.equal(params[key], value), key


def test_a_loss_without_a_pure_form_runs_eagerly_and_says_so(caplog, batches):
    class UsersOwnBC(LossModule):
        """A user's LossModule with a forward only (no inputs / terms split)."""

        def __init__(self, actor):
            super().__init__()
            self.convert_to_functional(actor, "actor_network")

        def forward(self, td):
            role = td["performant"]
            with self.actor_network_params.to_module(self.actor_network):
                dist = self.actor_network.get_dist(role.select("observation"))
            return TensorDict({"loss_actor": -dist.log_prob(role["action"]).mean()}, [])

    def build():
        torch.manual_seed(3)
        loss = UsersOwnBC(make_actor(OBS_DIM, ACT_DIM, hidden_cells=(16,)))
        return {"actor": loss}, [torch.optim.Adam(loss.parameters(), lr=1e-3)]

    _assert_trains_eagerly(build, batches, caplog, "UsersOwnBC has no inputs / terms split (not a PureLoss)")


def test_a_network_the_pure_form_cannot_call_trains_eagerly_and_says_so(caplog, batches):
    def build():
        torch.manual_seed(3)
        actor = make_actor(OBS_DIM, ACT_DIM, hidden_cells=(16,))
        wrapped = ProbabilisticTensorDictSequential(
            TensorDictSequential(actor.module[0]), actor.module[1]
        )  # the network inside one more sequential: not one module wrapped in a TensorDictModule
        loss = WeightedBCLoss(wrapped, role="performant")
        return {"actor": loss}, [torch.optim.Adam(loss.parameters(), lr=1e-3)]

    _assert_trains_eagerly(build, batches, caplog, "is not a network followed by a loc/scale distribution")


def test_a_step_that_fails_to_compile_runs_eagerly_from_the_same_random_state(caplog, monkeypatch, batches):
    def broken_compile(fn, **kwargs):
        def fails(*args):
            raise RuntimeError("no C++ compiler found\nsecond line")

        return fails

    _, eager_params, eager_rng = run(MultiLossStepper(*spoildice("normal", 1e-4)), batches)
    monkeypatch.setattr(torch, "compile", broken_compile)
    stepper = CompiledStepper(*spoildice("normal", 1e-4))
    with caplog.at_level(logging.WARNING, logger="spoil_torchrl.trainers.compiled"):
        _, params, rng = run(stepper, batches)
    assert not stepper.compiled
    assert caplog.text.count("did not compile (RuntimeError: no C++ compiler found); it runs eagerly") == 1
    assert torch.equal(rng, eager_rng)
    for key, value in eager_params.items():
        assert torch.equal(params[key], value), key


def test_compiled_stepper_keeps_the_eager_state_dict():
    losses, optimizers = spoildice("normal", 1e-4)
    eager = MultiLossStepper(losses, optimizers)
    compiled = CompiledStepper.from_stepper(eager)
    assert compiled.losses == eager.losses and compiled.optimizers == eager.optimizers
    assert compiled.state_dict().keys() == eager.state_dict().keys()


def test_more_steppers_than_dynamos_recompile_limit_all_compile():
    """Dynamo recompiles one code object at most 8 times; every stepper has its own, so a process (a notebook,
    this test suite) can build any number."""
    steppers = []
    for i in range(9):  # named apart: no two steppers can share a compiled graph
        loss = filtered_bc()[0]["actor"]
        steppers.append(CompiledStepper({f"actor_{i}": loss}, [sgd(loss.parameters())]))
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
    eager_out, eager_params, _ = run(MultiLossStepper(*spoildice("normal", 10.0, (256, 256))), batches)
    compiled = CompiledStepper(*spoildice("normal", 10.0, (256, 256)))
    with matmul_precision("medium"):
        out, params, _ = run(compiled, batches)
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


def test_a_compiled_stepper_steps_adam_straight_once_compiled(monkeypatch, batches):
    losses, optimizers = adam(*spoildice("normal", 1e-4))
    stepper = CompiledStepper(losses, optimizers)
    calls = []
    original = torch.optim.Adam.step
    monkeypatch.setattr(
        torch.optim.Adam, "step", lambda self, *a, **k: calls.append(1) or original(self, *a, **k)
    )
    for batch in batches[:3]:
        stepper.step(None, batch)
    assert stepper.compiled
    assert len(calls) == len(optimizers)  # the first compiled step's only: it creates the state


def test_use_fused_adam_reaches_wrapped_adam_and_leaves_other_optimizers():
    losses, optimizers = adam(*dwbc())
    optimizers[1] = StepEvery(optimizers[1], 2)
    plain = sgd(losses["dwbc"].parameters())
    use_fused_adam([*optimizers, plain])
    assert optimizers[0].param_groups[0]["fused"] and optimizers[1].optimizer.param_groups[0]["fused"]
    assert "fused" not in plain.param_groups[0] or not plain.param_groups[0]["fused"]
