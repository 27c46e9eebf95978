"""A state network's values and its gradient in the input, in the form whose gradient in the parameters costs
the least: what a DICE dual's gradient penalty :math:`c\\,E\\lVert \\nabla_s \\nu(\\tilde s) \\rVert^2` needs.

Autograd's second derivative of a ReLU network does more products than the penalty needs. The input gradient
of a ReLU MLP is a chain of products with the weights, masked by where each pre-activation is positive:
:math:`\\nabla_s \\nu = W_1^\\top D_1 W_2^\\top D_2 \\cdots W_L^\\top` with :math:`D_l = \\mathrm{diag}(z_l > 0)`. The
masks are piecewise constant, so the penalty's gradient in the parameters flows only through the weights of that
chain (ReLU's second derivative is zero almost everywhere). Autograd does not know that: the derivative of
ReLU's backward in its input is a tensor of zeros (``zeros_like`` in PyTorch's derivative formulas), and that
tensor is then sent back through the whole forward pass, two more matrix products per layer on every penalty
point, all of whose rows are zero. :func:`values_and_input_gradient` writes the chain out for a network that is
a plain ``Linear`` / ``ReLU`` sequence (what :func:`~spoil_torchrl.modules.make_value_network` builds) with
masks that carry no gradient (taken from detached layer outputs), so the penalty's gradient costs exactly the
products it needs; any other
network goes through autograd (:func:`torch.func.grad`). The two agree to float rounding (the sums run in
another order), which is why the form is chosen per loss (``DICELoss.penalty_form``).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn
from torch.func import grad
from torch.nn import functional as F

#: The forms of the penalty's input gradient: autograd's (any network), or the ReLU chain written out.
PENALTY_FORMS = ("autograd", "relu_chain")


def relu_chain_layers(module: nn.Module) -> list[str] | None:
    """The parameter prefixes of the ``Linear`` layers of ``module`` when it is a plain chain ``Linear, ReLU,
    Linear, ..., Linear`` (an :class:`torch.nn.Sequential`, e.g. TorchRL's ``MLP``) with one output, else ``None``.

    Examples:
        >>> relu_chain_layers(nn.Sequential(nn.Linear(3, 8), nn.ReLU(), nn.Linear(8, 1)))
        ['0', '2']
        >>> relu_chain_layers(nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 1))) is None
        True
    """
    if not isinstance(module, nn.Sequential):
        return None
    children = list(module.named_children())
    if not children or len(children) % 2 == 0:
        return None
    layers = []
    for i, (name, child) in enumerate(children):
        expected = nn.Linear if i % 2 == 0 else nn.ReLU
        if type(child) is not expected:
            return None
        if expected is nn.Linear:
            if child.bias is None:
                return None
            layers.append(name)
    return layers if children[-1][1].out_features == 1 else None


def _relu_forward(
    layers: list[str], params: dict[str, torch.Tensor], states: torch.Tensor
) -> tuple[torch.Tensor, list[torch.Tensor]]:
    r"""The chain's output at ``states`` and its hidden layers' outputs :math:`h_l = \max(z_l, 0)` (where they
    are positive is the mask :math:`D_l`)."""
    h, hidden = states, []
    for i, prefix in enumerate(layers):
        h = F.linear(h, params[f"{prefix}.weight"], params[f"{prefix}.bias"])
        if i < len(layers) - 1:
            h = torch.relu(h)
            hidden.append(h)
    return h, hidden


def _relu_chain(
    layers: list[str], params: dict[str, torch.Tensor], states: torch.Tensor, value_rows: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(input gradient, values of the first value_rows states)`` of the ReLU chain ``layers`` (see the module
    docstring). Only the first ``value_rows`` states run forward with their parameters' gradient: the other
    rows only give masks, which carry none.

    The masks are taken as ReLU's backward takes them (where the layer's output is positive) from float
    outputs: boolean tensors are slow in the compiled CPU kernels (a comparison stored as ``bool`` took ten
    times a float kernel of the same size)."""
    values, hidden = _relu_forward(layers, params, states[:value_rows])
    hidden = [h.detach() for h in hidden]
    if value_rows < states.shape[0]:
        frozen = {k: v.detach() for k, v in params.items()}
        _, rest = _relu_forward(layers, frozen, states[value_rows:])
        hidden = [torch.cat([a, b]) for a, b in zip(hidden, rest, strict=True)]
    g = params[f"{layers[-1]}.weight"].expand(states.shape[0], -1)
    for prefix, h in zip(reversed(layers[:-1]), reversed(hidden), strict=True):
        g = torch.where(h > 0, g, 0.0) @ params[f"{prefix}.weight"]
    return g, values.reshape(value_rows)


def values_and_input_gradient(
    network: Callable,
    params: dict[str, torch.Tensor],
    states: torch.Tensor,
    *,
    layers: list[str] | None,
    value_rows: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(∇_s ν(s), ν(s[:value_rows]))`` of a state network at ``states`` ([N, d] and [value_rows]),
    differentiable in ``params``: the penalty's input gradient at every point, and the values of the first
    ``value_rows`` (a DICE dual's current states, the first rows of its penalty points).

    ``network(params, states)`` is the network as a function (a :class:`~spoil_torchrl.objectives.pure.PureNetwork`).
    With ``layers`` (:func:`relu_chain_layers` of its module) the ReLU chain is written out, so the gradient of a
    penalty on the result in the parameters skips the products autograd spends on zeros; with ``None`` it is
    autograd's (:func:`torch.func.grad`). Both give the same values and gradients up to float rounding.

    Examples:
        >>> net = nn.Sequential(nn.Linear(3, 8), nn.ReLU(), nn.Linear(8, 1))
        >>> params = dict(net.named_parameters())
        >>> def call(p, s): return torch.func.functional_call(net, p, (s,))
        >>> s = torch.randn(5, 3)
        >>> g1, v1 = values_and_input_gradient(call, params, s, layers=relu_chain_layers(net), value_rows=2)
        >>> g2, v2 = values_and_input_gradient(call, params, s, layers=None, value_rows=2)
        >>> torch.allclose(g1, g2), torch.allclose(v1, v2), v1.shape
        (True, True, torch.Size([2]))
    """
    if layers is not None:
        return _relu_chain(layers, params, states, value_rows)

    def values_with_sum(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = network(params, x).reshape(x.shape[0])
        return out.sum(), out

    grads, values = grad(values_with_sum, has_aux=True)(states)
    return grads, values[:value_rows]
