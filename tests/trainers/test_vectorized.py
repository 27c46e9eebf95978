"""Several seeds in one vmapped step: each seed's numbers are those of its own steps (float tolerance), drawn
from its own random stream; the stacked state goes back into every seed's stepper and resumes exactly."""

from __future__ import annotations

import logging

import pytest
import torch

from spoil_torchrl.trainers import MultiLossStepper, StepEvery
from spoil_torchrl.trainers.vectorized import NotVectorizable, VectorizedStepper
from tests.conftest import dual_batch
from tests.trainers.steppers import (
    STEPS,
    adam,
    coptidice,
    demodice_s,
    discriminators,
    dwbc,
    filtered_bc,
    parameters_of,
    safedice,
    spoildice,
)

pytestmark = pytest.mark.compiles

SEEDS = 3


def _seeded(build, seed: int, **changes):
    """``build()`` with its weights moved by a seed's own noise (every seed starts elsewhere) and the settings
    ``changes`` applied to the losses that have them."""
    losses, optimizers = build()
    torch.manual_seed(100 + seed)
    with torch.no_grad():
        for loss in losses.values():
            for p in loss.parameters():
                p.add_(0.05 * torch.randn_like(p))
            for key, value in changes.items():
                if hasattr(loss, key):
                    setattr(loss, key, value)
    return losses, optimizers


def _stream(seed: int) -> torch.Tensor:
    torch.manual_seed(11 + seed)
    return torch.get_rng_state()


@pytest.fixture(scope="module")
def seed_batches():
    torch.manual_seed(5)
    return [[dual_batch(n_unl=64, n_init=16) for _ in range(STEPS)] for _ in range(SEEDS)]


def _each_seed_alone(build, seed_batches, changes=None):
    """Every seed's eager steps, one seed after another: outputs, parameters and random stream after."""
    out = []
    for seed, batches in enumerate(seed_batches):
        stepper = MultiLossStepper(*_seeded(build, seed, **(changes or {}).get(seed, {})))
        torch.set_rng_state(_stream(seed))
        outputs = [stepper.step(None, batch.clone()) for batch in batches]
        out.append((outputs, parameters_of(stepper.losses), torch.get_rng_state()))
    return out


def _vectorized(build, seed_batches, compile: bool, changes=None):
    steppers = [MultiLossStepper(*_seeded(build, s, **(changes or {}).get(s, {}))) for s in range(SEEDS)]
    stepper = VectorizedStepper(steppers, [_stream(s) for s in range(SEEDS)], compile=compile)
    outputs = [stepper.step(None, [b[t].clone() for b in seed_batches]) for t in range(STEPS)]
    stepper.sync()
    return stepper, outputs


def _assert_matches(stepper, outputs, alone) -> None:
    for seed, (seed_outputs, seed_params, seed_rng) in enumerate(alone):
        where = f"seed {seed}"
        assert torch.equal(stepper.rng_states[seed][0], seed_rng)  # the seed's own draws, in its order
        for t, expected in enumerate(seed_outputs):
            assert sorted(outputs[t].keys()) == sorted(expected.keys())
            for key in expected.keys():
                torch.testing.assert_close(
                    outputs[t][key][seed],
                    expected[key],
                    rtol=1e-4,
                    atol=1e-5,
                    msg=lambda m, k=key: f"{k}: {m}",
                )
        params = parameters_of(stepper.steppers[seed].losses)
        for key, value in seed_params.items():
            torch.testing.assert_close(
                params[key], value, rtol=1e-4, atol=1e-5, msg=lambda m, k=key, w=where: f"{w} {k}: {m}"
            )


@pytest.mark.parametrize(
    "build",
    [
        pytest.param(lambda: spoildice("normal", 1e-4), id="spoildice-penalty"),
        pytest.param(lambda: spoildice("tanh_normal", 0.0), id="spoildice-tanh-no-penalty"),
        pytest.param(demodice_s, id="demodice-s"),
        pytest.param(safedice, id="safedice"),
        # without chi: on these random batches chi's worst case puts all its mass on one of two near-tied
        # samples (KL = log 64, the maximum), so which one wins, and chi's next gradient, turns on the last bit;
        # chi is compared with the eager step in test_compiled.py, over fewer steps
        pytest.param(lambda: coptidice(0.0), id="coptidice-no-chi"),
        pytest.param(filtered_bc, id="filtered-bc"),
        pytest.param(dwbc, id="dwbc"),
        pytest.param(discriminators, id="discriminators"),
    ],
)
def test_vectorized_steps_match_each_seeds_own_steps(build, seed_batches):
    """The vmapped update (eager here: compiling every form would take minutes of the suite) against each
    seed's eager steps, for every loss of the package."""
    stepper, outputs = _vectorized(build, seed_batches, compile=False)
    _assert_matches(stepper, outputs, _each_seed_alone(build, seed_batches))
    stacked = next(iter(next(iter(stepper.params.values())).values()))
    assert not torch.equal(stacked[0], stacked[1])  # the seeds went their own ways


def test_compiled_vectorized_steps_match_each_seeds_own_steps(seed_batches):
    build = lambda: spoildice("normal", 10.0)  # noqa: E731
    stepper, outputs = _vectorized(build, seed_batches, compile=True)
    assert stepper.compiled, "the vectorised step fell back to eager"
    _assert_matches(stepper, outputs, _each_seed_alone(build, seed_batches))


def test_seeds_may_differ_in_what_a_form_takes_per_seed_and_nothing_else(seed_batches):
    """SafeDICE's alpha and reward standardisation come from each seed's discriminator; gamma is a setting."""
    alphas = {0: {"alpha": 0.2}, 1: {"alpha": 0.5, "reward_std": 2.0}, 2: {"alpha": 0.7, "reward_mean": 0.3}}
    stepper, outputs = _vectorized(safedice, seed_batches, compile=False, changes=alphas)
    _assert_matches(stepper, outputs, _each_seed_alone(safedice, seed_batches, alphas))
    assert outputs[0]["dice.alpha"].tolist() == pytest.approx([0.2, 0.5, 0.7])
    steppers = [MultiLossStepper(*_seeded(safedice, s, **({"gamma": 0.9} if s else {}))) for s in range(2)]
    with pytest.raises(NotVectorizable, match="seed 1: SafeDICELoss 'dice' has other settings \\(gamma\\)"):
        VectorizedStepper(steppers, [_stream(0), _stream(1)])


def test_the_stacked_state_resumes_exactly(seed_batches):
    """Adam's state and DWBC's every-2nd-step discriminator: stop after 2 steps, load the state into freshly
    built seeds, go on; the same as 4 steps in one go."""

    def build():
        losses, optimizers = adam(*dwbc())
        return losses, [optimizers[0], StepEvery(optimizers[1], 2)]

    def fresh():
        steppers = [MultiLossStepper(*_seeded(build, s)) for s in range(SEEDS)]
        return VectorizedStepper(steppers, [_stream(s) for s in range(SEEDS)], compile=False)

    def steps(stepper, ts):
        for t in ts:
            stepper.step(None, [b[t].clone() for b in seed_batches])

    whole = fresh()
    steps(whole, range(STEPS))
    whole.sync()
    first = fresh()
    steps(first, range(2))
    state = first.state_dict()
    assert state["seeds"][0]["optimizers"][1]["calls"] == 2
    second = fresh()
    second.load_state_dict(state)
    steps(second, range(2, STEPS))
    second.sync()
    for seed in range(SEEDS):
        expected = parameters_of(whole.steppers[seed].losses)
        for key, value in parameters_of(second.steppers[seed].losses).items():
            assert torch.equal(value, expected[key]), f"seed {seed} {key}"
        adam_state = whole.steppers[seed].optimizers[0].state_dict()["state"]
        for index, entry in second.steppers[seed].optimizers[0].state_dict()["state"].items():
            assert torch.equal(entry["exp_avg"], adam_state[index]["exp_avg"])


def test_steppers_of_another_structure_are_refused():
    a = MultiLossStepper(*filtered_bc())
    b = MultiLossStepper(*spoildice("normal", 0.0))
    with pytest.raises(NotVectorizable, match="seed 1 trains other losses"):
        VectorizedStepper([a, b], [_stream(0), _stream(1)])


def test_a_vectorized_update_that_fails_to_compile_runs_eagerly_and_says_so(
    caplog, monkeypatch, seed_batches
):
    def broken_compile(fn, **kwargs):
        def fails(*args):
            raise RuntimeError("no C++ compiler found\nsecond line")

        return fails

    build = lambda: spoildice("normal", 1e-4)  # noqa: E731
    monkeypatch.setattr(torch, "compile", broken_compile)
    with caplog.at_level(logging.WARNING, logger="spoil_torchrl.trainers.compiled"):
        stepper, outputs = _vectorized(build, seed_batches, compile=True)
    assert not stepper.compiled
    assert (
        caplog.text.count("the vectorised update did not compile (RuntimeError: no C++ compiler found)") == 1
    )
    _assert_matches(stepper, outputs, _each_seed_alone(build, seed_batches))
