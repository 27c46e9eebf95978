"""What every loss of the package must do, one parametrised module in the style of TorchRL's ``test/objectives``:
its outputs are its ``out_keys`` (scalars under ``mean``), ``state_dict`` carries everything its outputs depend
on, ``set_keys`` renames what it reads and refuses keys it does not know, it refuses the reductions it cannot
honour, it leaves its input as it was apart from the entries it documents writing, it names a missing role and a
missing annotation of a role (with what writes it), its keyword call returns its TensorDict call's outputs, and
its compiled update (``fullgraph=True``) gives the eager gradients. Each loss's own module tests its equations."""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field

import pytest
import torch
from tensordict import TensorDictBase
from torchrl.objectives import LossModule

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
from spoil_torchrl.trainers.compiled import (
    _with_own_code,
    detached,
    pure_losses,
    step_inputs,
    update_gradients,
)
from tests.conftest import ACT_DIM, OBS_DIM, dual_batch


def assert_keyword_call_matches(loss: LossModule, batch: TensorDictBase) -> None:
    """``loss(**entries)`` returns the outputs of ``loss(tensordict)`` in ``out_keys`` order (same draws)."""
    torch.manual_seed(7)
    expected = loss(batch.clone())
    torch.manual_seed(7)
    values = loss(**{"_".join(key): batch.get(key) for key in loss.in_keys})
    values = values if isinstance(values, tuple) else (values,)
    assert len(values) == len(loss.out_keys)
    for key, value in zip(loss.out_keys, values, strict=True):
        torch.testing.assert_close(value, expected[key], msg=lambda m, key=key: f"{key}: {m}")


def assert_compiles_whole(loss: LossModule, batch: TensorDictBase) -> None:
    """The loss's update (its ``terms`` under ``grad_and_value``, the gradient penalty's double backward
    included) traces as one graph, and its gradients are those of ``forward``'s ``loss_*`` terms under
    autograd, from the same random draws."""
    losses = {"loss": loss}
    params = {"loss": loss.term_parameters()}
    torch.manual_seed(7)
    inputs = step_inputs(losses, pure_losses(losses), batch.clone())
    # a code object of its own per loss: Dynamo recompiles one code object at most 8 times in a process
    update = _with_own_code(update_gradients(losses), f"update_{type(loss).__name__}_{id(loss)}")
    compiled = torch.compile(update, backend="aot_eager", fullgraph=True)
    grads, _ = compiled(detached(params), inputs)
    torch.manual_seed(7)
    out = loss(batch.clone())
    sum(value for key, value in out.items() if key.startswith("loss_")).backward()
    moved = 0
    for name, p in params["loss"].items():
        expected = torch.zeros_like(p) if p.grad is None else p.grad
        torch.testing.assert_close(grads["loss"][name], expected, msg=lambda m, name=name: f"{name}: {m}")
        moved += bool(expected.abs().sum() > 0)
    assert moved > 0, "no parameter has a gradient"


def _value(**kwargs):
    return make_value_network(OBS_DIM, hidden_cells=(16, 16), **kwargs)


def _safedice_batch():
    batch = dual_batch()
    batch["unlabeled", "log_ratio_nonpreferred"] = torch.randn(32, 1)
    return batch


def _two_constraints_batch():
    """A batch with two support indicators per unlabeled transition (``safe_support`` ``[n, 2]``)."""
    batch = dual_batch()
    first = batch["unlabeled", "safe_support"]
    batch["unlabeled", "safe_support"] = torch.cat([first, 1.0 - first * (torch.rand_like(first) < 0.5)], -1)
    return batch


def _renamed(role: str, new_role: str, key: str | None = None, new_key: str | None = None):
    """A batch change that moves ``role`` to ``new_role`` (and its entry ``key`` to ``new_key``)."""

    def rename(batch: TensorDictBase) -> TensorDictBase:
        batch = batch.clone()
        batch.rename_key_(role, new_role)
        if key is not None:
            batch[new_role].rename_key_(key, new_key)
        return batch

    return rename


@dataclass
class Case:
    """One loss as the contract tests build and feed it."""

    make: Callable[..., LossModule]
    batch: Callable[[], TensorDictBase] = dual_batch
    #: ``set_keys`` arguments and the same renaming done to the batch
    set_keys: dict = field(default_factory=dict)
    rename: Callable[[TensorDictBase], TensorDictBase] = lambda batch: batch
    unknown_key: str = "no_such_key"
    #: a role it reads, deleted to check the error
    role: str = "init"
    #: entries of the ``unlabeled`` role it reads, each deleted to check the error, with what the error must
    #: say writes it
    annotations: tuple = ()
    #: the entries it writes into its input (``(role, key)``)
    writes: tuple = ()
    #: the losses it computes per sample (``reduction="none"`` / ``"sum"``); none: it refuses other reductions
    per_sample: tuple = ()
    #: ``state_dict`` entries beyond the networks' (its dual variables)
    state_has: tuple = ()
    #: keyword arguments that make its outputs deterministic (no random penalty points) for the comparisons
    plain: dict = field(default_factory=dict)


def _spoildice_case(constraints: int) -> Case:
    """SpoilDICELoss with one constraint (the paper's) or several (one support indicator each)."""
    return Case(
        lambda **kw: SpoilDICELoss(_value(), gamma=0.9, constraints=constraints, **kw),
        batch=dual_batch if constraints == 1 else _two_constraints_batch,
        set_keys={"unlabeled": "pool", "support": "support_hat", "weight": "w"},
        rename=_renamed("unlabeled", "pool", "safe_support", "support_hat"),
        unknown_key="reward",
        annotations=(("log_ratio_performant", "log_ratio_module"), ("safe_support", "SupportEstimator")),
        writes=(("unlabeled", "dice_weight"), ("unlabeled", "dice_advantage")),
        state_has=("lagrange",),
        plain={"gradient_penalty": 0.0},
    )


CASES = {
    "spoildice": _spoildice_case(constraints=1),
    "spoildice_two_constraints": _spoildice_case(constraints=2),
    "demodice": Case(
        lambda **kw: DemoDICELoss(_value(), gamma=0.9, alpha=0.1, **kw),
        set_keys={"regularization": "pool", "reward": "r", "weight": "w"},
        rename=_renamed("unlabeled", "pool", "log_ratio_performant", "r"),
        unknown_key="support",
        annotations=(("log_ratio_performant", "log_ratio_module"),),
        writes=(("unlabeled", "dice_weight"), ("unlabeled", "dice_advantage")),
        plain={"gradient_penalty": 0.0},
    ),
    "safedice": Case(
        lambda **kw: SafeDICELoss(_value(), gamma=0.9, alpha=0.3, **kw),
        batch=_safedice_batch,
        set_keys={"unlabeled": "pool", "logit": "c_n", "weight": "w"},
        rename=_renamed("unlabeled", "pool", "log_ratio_nonpreferred", "c_n"),
        unknown_key="reward",
        annotations=(("log_ratio_nonpreferred", "log_ratio_module"),),
        writes=(("unlabeled", "dice_weight"), ("unlabeled", "dice_advantage")),
        plain={"gradient_penalty": 0.0},
    ),
    "coptidice": Case(
        lambda **kw: COptiDICELoss(
            _value(), _value(out_key="chi"), gamma=0.9, alpha=0.5, cost_limit=0.3, **kw
        ),
        set_keys={"unlabeled": "pool", "weight": "w"},
        rename=_renamed("unlabeled", "pool"),
        unknown_key="logit",
        annotations=((("next", "reward"), "per-step reward"), (("next", "cost"), "per-step reward and cost")),
        writes=(("unlabeled", "dice_weight"), ("unlabeled", "dice_advantage")),
        state_has=("lagrange_param", "tau_param"),
        plain={"gradient_penalty": 0.0},
    ),
    "dwbc": Case(
        lambda **kw: DWBCLoss(
            make_actor(OBS_DIM, ACT_DIM, hidden_cells=(16,), distribution="normal"),
            make_discriminator(OBS_DIM, ACT_DIM, hidden_cells=(16,), extra_inputs={"policy_log_prob": 1}),
            **kw,
        ),
        batch=lambda: dual_batch(n_safe=4, n_perf=4, n_unl=4),
        set_keys={"unlabeled": "pool"},
        rename=_renamed("unlabeled", "pool"),
        role="performant",
    ),
    "discriminator": Case(
        lambda **kw: PUDiscriminatorLoss(make_discriminator(OBS_DIM, ACT_DIM, hidden_cells=(16, 16)), **kw),
        set_keys={"unlabeled": "pool"},
        rename=_renamed("unlabeled", "pool"),
        unknown_key="expert",
        role="performant",
        per_sample=("loss_positive", "loss_unlabeled"),
        plain={"gradient_penalty": 0.0},
    ),
    "weighted_bc": Case(
        lambda **kw: WeightedBCLoss(make_actor(OBS_DIM, ACT_DIM, hidden_cells=(16,)), **kw),
        set_keys={"role": "pool"},
        rename=_renamed("performant", "pool"),
        unknown_key="observation",
        role="performant",
        per_sample=("loss_actor",),
    ),
}
NAMES = list(CASES)


def _outputs(loss: LossModule, batch: TensorDictBase, seed: int = 7) -> dict[str, torch.Tensor]:
    torch.manual_seed(seed)
    return {key: value.detach() for key, value in loss(batch.clone()).items()}


def _assert_same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        torch.testing.assert_close(a[key], b[key], msg=lambda m, key=key: f"{key}: {m}")


@pytest.mark.parametrize("name", NAMES)
def test_outputs_are_the_out_keys_and_scalars(name):
    case = CASES[name]
    loss = case.make()
    out = loss(case.batch())
    assert set(out.keys()) == set(loss.out_keys)
    assert any(key.startswith("loss_") for key in out.keys())
    for key, value in out.items():
        assert value.shape == torch.Size([]) and torch.isfinite(value), key


@pytest.mark.parametrize("name", NAMES)
def test_state_dict_round_trip(name):
    case = CASES[name]
    a, b = case.make(**case.plain), case.make(**case.plain)
    for p in a.parameters():  # the dual variables too: a's state differs from b's everywhere
        p.data.add_(0.1 * torch.randn_like(p))
    batch = case.batch()
    assert set(case.state_has) <= set(a.state_dict())
    before, expected = _outputs(b, batch), _outputs(a, batch)
    assert any(not torch.allclose(v, expected[k]) for k, v in before.items() if k.startswith("loss_"))
    b.load_state_dict(a.state_dict())
    _assert_same(_outputs(b, batch), expected)


@pytest.mark.parametrize("name", NAMES)
def test_set_keys_reads_the_renamed_entries_and_refuses_unknown_keys(name):
    case = CASES[name]
    loss, renamed_loss = case.make(**case.plain), case.make(**case.plain)
    renamed_loss.load_state_dict(loss.state_dict())
    renamed_loss.set_keys(**case.set_keys)
    batch = case.batch()
    renamed = case.rename(batch)
    assert set(renamed_loss.in_keys) <= set(renamed.keys(True, True)) and renamed_loss.in_keys != loss.in_keys
    _assert_same(_outputs(renamed_loss, renamed), _outputs(loss, batch))
    with pytest.raises(ValueError, match="not an accepted tensordict key"):
        renamed_loss.set_keys(**{case.unknown_key: "x"})


@pytest.mark.parametrize("name", NAMES)
def test_reductions_it_cannot_honour_are_refused(name):
    case = CASES[name]
    assert case.make().reduction == "mean" and case.make(reduction="mean").reduction == "mean"
    if not case.per_sample:
        for reduction in ("none", "sum"):
            with pytest.raises(ValueError, match="reduction"):
                case.make(reduction=reduction)
        return
    with pytest.raises(ValueError, match="reduction"):
        case.make(reduction="max")
    per_sample = case.make(reduction="none", **case.plain)
    batch = case.batch()
    values = _outputs(per_sample, batch)
    for reduction, fn in (("mean", torch.mean), ("sum", torch.sum)):
        reduced = case.make(reduction=reduction, **case.plain)
        reduced.load_state_dict(per_sample.state_dict())
        out = _outputs(reduced, batch)
        for key in case.per_sample:
            assert values[key].dim() == 1, key
            torch.testing.assert_close(out[key], fn(values[key]), msg=lambda m, key=key: f"{key}: {m}")


@pytest.mark.parametrize("name", NAMES)
def test_the_input_is_left_as_it_was_but_for_the_documented_entries(name):
    case = CASES[name]
    batch = case.batch()
    before = batch.clone()
    case.make()(batch)
    written = set(batch.keys(True, True)) - set(before.keys(True, True))
    assert written == set(case.writes)
    for key in before.keys(True, True):
        assert torch.equal(batch.get(key), before.get(key)), key
        assert not batch.get(key).requires_grad, key


@pytest.mark.parametrize("name", NAMES)
def test_a_missing_role_is_named(name):
    case = CASES[name]
    batch = case.batch()
    del batch[case.role]
    with pytest.raises(KeyError, match=f"no role '{case.role}'"):
        case.make()(batch)


@pytest.mark.parametrize(
    "name, key, writer", [(name, *entry) for name in NAMES for entry in CASES[name].annotations]
)
def test_a_missing_annotation_is_named_with_what_writes_it(name, key, writer):
    case = CASES[name]
    batch = case.batch()
    del batch["unlabeled", key]
    named = re.escape(f"role 'unlabeled' has no entry {key!r} (")
    with pytest.raises(KeyError, match=f"{named}.*{writer}"):
        case.make()(batch)


@pytest.mark.parametrize("name", NAMES)
def test_the_keyword_call_returns_the_tensordict_calls_outputs(name):
    case = CASES[name]
    assert_keyword_call_matches(case.make(), case.batch())


@pytest.mark.compiles
@pytest.mark.parametrize("name", NAMES)
def test_the_compiled_update_gives_the_eager_gradients(name):
    case = CASES[name]
    assert_compiles_whole(case.make(), case.batch())


def test_roles_read_are_the_roles_of_the_losses_in_keys():
    from spoil_torchrl.objectives.keys import roles_read

    roles = ["safe", "performant", "unlabeled", "init"]
    dice = SpoilDICELoss(make_value_network(OBS_DIM, hidden_cells=(8,)))
    bc = WeightedBCLoss(make_actor(OBS_DIM, ACT_DIM, hidden_cells=(8,)), role="unlabeled")
    assert roles_read([dice, bc], roles) == ["unlabeled", "init"]
    performant = WeightedBCLoss(
        make_actor(OBS_DIM, ACT_DIM, hidden_cells=(8,)), role="performant", weight=None
    )
    assert roles_read([performant], roles) == ["performant"]

    class OwnWay(torch.nn.Module):  # reads the batch without naming roles: every role is drawn
        in_keys = ["observation"]

    assert roles_read([dice, OwnWay()], roles) is None
