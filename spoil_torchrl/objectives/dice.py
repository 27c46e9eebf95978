"""What every DICE dual (SpoilDICE, DemoDICE, SafeDICE, COptiDICE) shares: one role's transitions and the
initial states read as plain tensors, its state networks evaluated on them, and their gradient penalty."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torch.func import grad

from spoil_torchrl.objectives.functional import check_reduction, gradient_penalty, penalty_points
from spoil_torchrl.objectives.keys import DICETransitions, dice_transitions, get_role, role_key
from spoil_torchrl.objectives.pure import PureLoss, PureNetwork, Tensors


def state_terms(
    network: PureNetwork, params: Tensors, x: Tensors, points: torch.Tensor | None, coefficient: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A state network (nu, COptiDICE's chi) at the initial, current and next states of ``x``, and its
    weighted gradient penalty :math:`c\\,E[\\lVert \\nabla_s \\nu(\\tilde s) \\rVert^2]` on ``points`` (0 when
    ``points`` is ``None``).

    The points (:func:`~spoil_torchrl.objectives.functional.penalty_points`) are the current states, then states
    between initial and current states, then states between :math:`s` and :math:`s'` (DemoDICE's reference
    form, with the dual's own role in place of its expert data). With the penalty on, the network runs once on
    the points, whose first rows are the current states: their values and the input gradient come from that one
    pass. The gradient is taken with :func:`torch.func.grad`, so the penalty trains the network's parameters
    both under autograd and in a compiled step.

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

    def values_with_sum(states: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = values(states)
        return out.sum(), out

    n, n0 = x["current"].shape[0], x["init"].shape[0]
    init_v, next_v = values(torch.cat([x["init"], x["following"]])).split([n0, n])
    if points is None:
        return init_v, values(x["current"]), next_v, init_v.new_zeros(())
    grads, on_points = grad(values_with_sum, has_aux=True)(points)
    norms = grads.reshape(grads.shape[0], -1).norm(dim=-1)
    return init_v, on_points[:n], next_v, coefficient * gradient_penalty(norms, target=None)


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

    def nu_terms(self, params: Tensors, x: Tensors) -> tuple[torch.Tensor, ...]:
        """nu at the initial, current and next states, and the weighted gradient penalty (0 when off)."""
        nu_params = {k.removeprefix("nu."): v for k, v in params.items() if k.startswith("nu.")}
        return state_terms(
            self.state_network("nu_network"), nu_params, x, x.get("points"), self.gradient_penalty
        )
