"""What every DICE LossModule does with its value network(s): read one role's transitions and the initial
states, and evaluate a state network on all of them at once."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey

from spoil_torchrl.objectives.functional import check_reduction
from spoil_torchrl.objectives.keys import DICETransitions, dice_transitions, role_key


class StateValues:
    """Mixin for DICE LossModules with a functional ``nu_network`` (and optionally more state networks).

    The host loss needs ``tensor_keys`` with ``init``, ``next`` and ``terminated`` entries, and calls
    :meth:`_setup_dual` in its ``__init__`` (further networks via ``convert_to_functional(network, "<name>")``).
    """

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
        self.gamma = float(gamma)
        self.gradient_penalty = float(gradient_penalty)

    def _values(self, name: str, states: dict[NestedKey, torch.Tensor]) -> torch.Tensor:
        """The functional network ``name`` (e.g. ``"nu_network"``) on a batch of states, shape ``[n]``."""
        n = next(iter(states.values())).shape[0]
        network = getattr(self, name)
        with getattr(self, f"{name}_params").to_module(network):
            out = network(TensorDict(states, [n]))
        return out.get(network.out_keys[0]).reshape(n)

    def _nu(self, states: dict[NestedKey, torch.Tensor]) -> torch.Tensor:
        return self._values("nu_network", states)

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

    def _on_transitions(
        self, name: str, t: DICETransitions
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The network ``name`` at the initial states, at s and at s' (one forward pass)."""
        n, n0 = t.batch_shape.numel(), next(iter(t.init.values())).shape[0]
        states = {k: torch.cat([t.init[k], t.current[k], t.following[k]]) for k in t.init}
        init_v, v, next_v = self._values(name, states).split([n0, n, n])
        return init_v, v, next_v
