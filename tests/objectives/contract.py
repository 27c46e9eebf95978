"""What every loss of the package must do, checked by each loss's test module: the keyword call gives the
TensorDict call's outputs, and the loss's update compiles as one graph (``fullgraph=True``) to the eager
gradients."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.objectives import LossModule

from spoil_torchrl.trainers.compiled import detached, pure_losses, step_inputs, update_gradients


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
    compiled = torch.compile(update_gradients(losses), backend="aot_eager", fullgraph=True)
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
