"""FusedAdamSteps: the fused Adam kernel called straight makes ``Adam.step``'s numbers bit for bit, keeps the
optimiser's state, schedules and hooks."""

from __future__ import annotations

import copy

import pytest
import torch

from spoil_torchrl.trainers import StepEvery
from spoil_torchrl.trainers.fused_adam import FusedAdamSteps, use_fused_adam

STEPS = 12


def _model(seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(5, 16), torch.nn.ReLU(), torch.nn.Linear(16, 3))


def _optimizers(model: torch.nn.Module, kind: str) -> list:
    first, second = list(model[0].parameters()), list(model[2].parameters())
    if kind == "adam":
        optimizers = [torch.optim.Adam(first, lr=1e-2), torch.optim.Adam(second, lr=3e-3, eps=1e-6)]
    elif kind == "adamw":
        optimizers = [torch.optim.AdamW(first + second, lr=1e-2, weight_decay=0.1)]
    elif kind == "amsgrad_maximize":
        optimizers = [
            torch.optim.Adam(first + second, lr=1e-2, amsgrad=True, maximize=True, weight_decay=0.01)
        ]
    elif kind == "two_groups":
        optimizers = [torch.optim.Adam([{"params": first}, {"params": second, "lr": 1e-3}], lr=1e-2)]
    elif kind == "step_every":
        optimizers = [torch.optim.Adam(first, lr=1e-2), StepEvery(torch.optim.Adam(second, lr=1e-2), 3)]
    else:
        raise ValueError(kind)
    use_fused_adam(optimizers)
    return optimizers


def _train(kind: str, direct: bool, *, schedule: bool = False, frozen_bias: bool = False):
    """``STEPS`` steps of a small regression through ``Adam.step`` (``direct=False``) or FusedAdamSteps."""
    model = _model()
    optimizers = _optimizers(model, kind)
    schedulers = [torch.optim.lr_scheduler.StepLR(o, 4, 0.5) for o in optimizers] if schedule else []
    steps = FusedAdamSteps(optimizers)
    gen = torch.Generator().manual_seed(1)
    for i in range(STEPS):
        x, y = torch.randn(32, 5, generator=gen), torch.randn(32, 3, generator=gen)
        for o in optimizers:
            o.zero_grad(set_to_none=True)
        ((model(x) - y) ** 2).mean().backward()
        if frozen_bias and i >= 4:
            model[2].bias.grad = None  # a parameter without a gradient is skipped, as Adam.step skips it
        if direct:
            steps.step()
        else:
            for o in optimizers:
                o.step()
        for s in schedulers:
            s.step()
    return model, optimizers


def _states(optimizers) -> list:
    return [copy.deepcopy(o.state_dict()) for o in optimizers]


def _assert_same(a, b) -> None:
    if torch.is_tensor(a):
        assert torch.equal(a, b), (a, b)
    elif isinstance(a, dict):
        assert a.keys() == b.keys()
        for k in a:
            _assert_same(a[k], b[k])
    elif isinstance(a, list | tuple):
        assert len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            _assert_same(x, y)
    else:
        assert a == b


@pytest.mark.parametrize("kind", ["adam", "adamw", "amsgrad_maximize", "two_groups", "step_every"])
def test_direct_fused_steps_are_adam_steps_bit_for_bit(kind):
    ref_model, ref_optims = _train(kind, direct=False)
    model, optims = _train(kind, direct=True)
    for p, q in zip(ref_model.parameters(), model.parameters(), strict=True):
        assert torch.equal(p, q)
    _assert_same(_states(ref_optims), _states(optims))


def test_direct_fused_steps_follow_the_schedule_and_skip_parameters_without_gradient():
    ref_model, ref_optims = _train("adam", direct=False, schedule=True, frozen_bias=True)
    model, optims = _train("adam", direct=True, schedule=True, frozen_bias=True)
    assert optims[0].param_groups[0]["lr"] == pytest.approx(1e-2 * 0.5**3)
    for p, q in zip(ref_model.parameters(), model.parameters(), strict=True):
        assert torch.equal(p, q)
    _assert_same(_states(ref_optims), _states(optims))


def test_an_optimizer_with_a_step_hook_steps_through_its_own_step():
    model = _model()
    (optim,) = _optimizers(model, "amsgrad_maximize")
    calls = []
    optim.register_step_post_hook(lambda *_: calls.append(1))
    steps = FusedAdamSteps([optim])
    for _ in range(3):
        model(torch.ones(2, 5)).sum().backward()
        steps.step()
    assert len(calls) == 3


def test_after_reset_the_new_state_tensors_are_the_ones_stepped():
    model, (optim,) = _train("adamw", direct=True)
    steps = FusedAdamSteps([optim])
    model(torch.ones(2, 5)).sum().backward()
    steps.step()  # through AdamW.step, then straight
    optim.load_state_dict(optim.state_dict())  # new state tensors (copies)
    steps.reset()
    model(torch.ones(2, 5)).sum().backward()
    before = optim.state_dict()["state"][0]["step"].item()
    steps.step()
    steps.step()
    assert optim.state_dict()["state"][0]["step"].item() == before + 2


def test_an_optimizer_loaded_behind_the_steps_back_is_stepped_with_its_new_state():
    ref_model, (ref,) = _train("adamw", direct=False)
    model, (optim,) = _train("adamw", direct=False)
    steps = FusedAdamSteps([optim])
    x = torch.ones(2, 5)
    for m, o, step in ((ref_model, ref, ref.step), (model, optim, steps.step)):
        for _ in range(2):
            o.zero_grad()
            m(x).sum().backward()
            step()
    optim.load_state_dict(copy.deepcopy(ref.state_dict()))  # new state tensors, without reset()
    for m, o, step in ((ref_model, ref, ref.step), (model, optim, steps.step)):
        o.zero_grad()
        m(x).sum().backward()
        step()
    for p, q in zip(ref_model.parameters(), model.parameters(), strict=True):
        assert torch.equal(p, q)
    _assert_same(_states([ref]), _states([optim]))
