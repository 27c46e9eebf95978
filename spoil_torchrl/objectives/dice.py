"""What every DICE dual (SpoilDICE, DemoDICE, SafeDICE, COptiDICE) shares: one role's transitions and the
initial states read as plain tensors, its state networks evaluated on them, and their gradient penalty."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn

from spoil_torchrl.objectives.functional import check_reduction, gradient_penalty, penalty_points
from spoil_torchrl.objectives.input_gradient import (
    PENALTY_FORMS,
    relu_chain_layers,
    values_and_input_gradient,
)
from spoil_torchrl.objectives.keys import DICETransitions, dice_transitions, get_role, role_key
from spoil_torchrl.objectives.pure import PureLoss, PureNetwork, Tensors


def state_terms(
    network: PureNetwork,
    params: Tensors,
    x: Tensors,
    points: torch.Tensor | None,
    coefficient: float,
    layers: list[str] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A state network (nu, COptiDICE's chi) at the initial, current and next states of ``x``, and its
    weighted gradient penalty :math:`c\\,E[\\lVert \\nabla_s \\nu(\\tilde s) \\rVert^2]` on ``points`` (0 when
    ``points`` is ``None``).

    The points (:func:`~spoil_torchrl.objectives.functional.penalty_points`) are the current states, then states
    between initial and current states, then states between :math:`s` and :math:`s'` (DemoDICE's reference
    form, with the dual's own role in place of its expert data). With the penalty on, the network runs once on
    the points, whose first rows are the current states: their values and the input gradient come from that one
    pass. The gradient is :func:`~spoil_torchrl.objectives.input_gradient.values_and_input_gradient`'s: autograd's
    (:func:`torch.func.grad`), or with ``layers`` (the network's ReLU chain) the chain written out, whose gradient
    in the parameters skips autograd's products on zeros. Either trains the network's parameters under autograd
    and in a compiled step.

    Examples:
        >>> from spoil_torchrl.modules import make_value_network
        >>> from spoil_torchrl.objectives import SpoilDICELoss
        >>> loss = SpoilDICELoss(make_value_network(2, hidden_cells=(8,)))
        >>> net = loss.state_network("nu_network")
        >>> params = net.parameters(loss.nu_network_params)
        >>> x = {"init": torch.randn(3, 2), "current": torch.randn(5, 2), "following": torch.randn(5, 2)}
        >>> init_v, v, next_v, penalty = state_terms(net, params, x, x["current"], coefficient=1.0)
        >>> init_v.shape, v.shape, next_v.shape, bool(penalty > 0)
        (torch.Size([3]), torch.Size([5]), torch.Size([5]), True)
    """

    def values(states: torch.Tensor) -> torch.Tensor:
        return network(params, states).reshape(states.shape[0])

    n, n0 = x["current"].shape[0], x["init"].shape[0]
    init_v, next_v = values(torch.cat([x["init"], x["following"]])).split([n0, n])
    if points is None:
        return init_v, values(x["current"]), next_v, init_v.new_zeros(())
    grads, current_v = values_and_input_gradient(network, params, points, layers=layers, value_rows=n)
    norms = grads.reshape(grads.shape[0], -1).norm(dim=-1)
    return init_v, current_v, next_v, coefficient * gradient_penalty(norms, target=None)


class DICELoss(PureLoss):
    """Base of the DICE duals: a functional ``nu_network`` (and optionally more state networks) over the
    transitions of one role (:attr:`dual_role`) and the initial states.

    A subclass needs ``tensor_keys`` with ``init``, ``next``, ``terminated``, ``weight`` and ``advantage``
    entries, calls :meth:`_setup_dual` in its ``__init__`` (further state networks via
    ``convert_to_functional(network, "<name>")``), and implements :meth:`terms` from :meth:`nu_terms` and its
    own inputs (:meth:`inputs` gives the role's states, ``terminated`` and the penalty's points). Its weights and
    advantage go into ``produced`` with :meth:`_produce`; ``forward`` writes them into the role.
    """

    functional_params = ("nu_network_params",)
    #: the inputs holding each penalised state network's points, in the order they are drawn
    penalised: tuple[str, ...] = ("points",)

    def _setup_dual(
        self, nu_network, *, gamma: float, gradient_penalty: float, reduction: str | None
    ) -> None:
        """Check and store what every DICE dual has: the discount, the nu gradient-penalty coefficient, the
        reduction (only ``"mean"``: a batch-level objective) and the functional nu network."""
        if not 0.0 < gamma < 1.0:
            raise ValueError(f"gamma must lie in (0, 1), got {gamma}")
        if gradient_penalty < 0:
            raise ValueError(f"gradient_penalty must be >= 0, got {gradient_penalty}")
        self.reduction = check_reduction(reduction, allowed=("mean",))
        self.convert_to_functional(nu_network, "nu_network")
        self.state_network("nu_network").in_key  # noqa: B018 (raises unless nu reads one entry)
        self.gamma = float(gamma)
        self.gradient_penalty = float(gradient_penalty)
        self._penalty_form, self._penalty_layers = "autograd", {}  # (penalty_form)

    @property
    def dual_role(self) -> NestedKey:
        """The role whose transitions the dual weights."""
        raise NotImplementedError

    def state_network(self, name: str) -> PureNetwork:
        """The functional state network ``name`` (e.g. ``"nu_network"``) as a :class:`PureNetwork` (made once)."""
        what = f"{type(self).__name__}'s {name}"
        return self._pure(
            name, lambda: PureNetwork(getattr(self, name), getattr(self, f"{name}_params"), what)
        )

    def term_parameters(self) -> dict[str, nn.Parameter]:
        nu = self.state_network("nu_network").parameters(self.nu_network_params)
        return {f"nu.{k}": v for k, v in nu.items()}

    def check_compilable(self) -> None:
        self.state_network("nu_network").check_compilable()

    @property
    def produces(self) -> dict[NestedKey, NestedKey]:
        role, keys = self.dual_role, self.tensor_keys
        return {role_key(role, keys.weight): role, role_key(role, keys.advantage): role}

    def _produce(self, produced: dict, weights: torch.Tensor, advantage: torch.Tensor) -> None:
        role, keys = self.dual_role, self.tensor_keys
        produced[role_key(role, keys.weight)] = weights
        produced[role_key(role, keys.advantage)] = advantage.detach()

    def _rows_shape(self, tensordict: TensorDictBase, role: NestedKey) -> torch.Size:
        return get_role(tensordict, role).get(self.tensor_keys.terminated).shape[:-1]

    def _role_in_keys(self, role: NestedKey, *entries: NestedKey) -> list[NestedKey]:
        """``in_keys`` of a dual over ``role``: its states, next states, ``terminated`` and ``entries``, and the
        initial states."""
        keys = self.tensor_keys
        state_keys = self.nu_network.in_keys
        current = [role_key(role, k) for k in state_keys]
        following = [role_key(role, role_key(keys.next, k)) for k in state_keys]
        extra = [role_key(role, k) for k in (keys.terminated, *entries)]
        return current + following + extra + [role_key(keys.init, k) for k in state_keys]

    def _transitions(self, tensordict: TensorDictBase, role: NestedKey) -> DICETransitions:
        keys = self.tensor_keys
        return dice_transitions(
            tensordict,
            role=role,
            init=keys.init,
            state_keys=self.nu_network.in_keys,
            next_key=keys.next,
            terminated_key=keys.terminated,
            loss_name=type(self).__name__,
        )

    def inputs(self, tensordict: TensorDictBase, produced: frozenset = frozenset()) -> Tensors:
        """The role's states (``current``, ``following``), the initial states (``init``), ``terminated`` and,
        when the penalty is on, the points of each penalised network (random, drawn here)."""
        t = self._transitions(tensordict, self.dual_role)
        key = self.state_network("nu_network").in_key
        out = {
            "init": t.init[key],
            "current": t.current[key],
            "following": t.following[key],
            "terminated": t.terminated,
        }
        if self.gradient_penalty != 0:
            for name in self.penalised:
                out[name] = penalty_points(t.init, t.current, t.following)[key]
        return out

    @property
    def penalty_form(self) -> str:
        """How the gradient penalty's input gradient is taken
        (:func:`~spoil_torchrl.objectives.input_gradient.values_and_input_gradient`): ``"autograd"`` (the
        default, any network) or ``"relu_chain"`` (state networks that are plain ReLU MLPs: the same values and
        gradients up to float rounding, with fewer products). Setting ``"relu_chain"`` checks every penalised
        network."""
        return self._penalty_form

    @penalty_form.setter
    def penalty_form(self, form: str) -> None:
        if form not in PENALTY_FORMS:
            raise ValueError(f"penalty_form must be one of {PENALTY_FORMS}, got {form!r}")
        layers = {}
        if form == "relu_chain":
            for name in self.penalised_networks:
                network = self.state_network(name)
                layers[name] = relu_chain_layers(network.network.module) if network.plain else None
                if layers[name] is None:
                    raise ValueError(
                        f"penalty_form='relu_chain' needs {type(self).__name__}'s {name} to be a plain "
                        "Linear/ReLU chain with one output (make_value_network builds one); use 'autograd'"
                    )
        self._penalty_form, self._penalty_layers = form, layers

    #: the state networks with a gradient penalty, in the order of :attr:`penalised`
    penalised_networks: tuple[str, ...] = ("nu_network",)

    def penalty_layers(self, name: str) -> list[str] | None:
        """The ReLU chain of the penalised network ``name`` under ``penalty_form="relu_chain"``, else ``None``."""
        return self._penalty_layers.get(name)

    def nu_terms(self, params: Tensors, x: Tensors) -> tuple[torch.Tensor, ...]:
        """nu at the initial, current and next states, and the weighted gradient penalty (0 when off)."""
        nu_params = {k.removeprefix("nu."): v for k, v in params.items() if k.startswith("nu.")}
        return state_terms(
            self.state_network("nu_network"),
            nu_params,
            x,
            x.get("points"),
            self.gradient_penalty,
            self.penalty_layers("nu_network"),
        )
