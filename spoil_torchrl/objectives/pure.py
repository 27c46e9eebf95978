"""Losses whose equations are pure functions of plain tensors: one form for the eager step and the compiled one.

Every loss of the package is a :class:`PureLoss`. Its ``forward`` is two calls:

* :meth:`PureLoss.inputs` (eager) reads the batch's tensors out of the tensordict, checks them, and draws the
  random numbers the loss needs (a gradient penalty's interpolation points), in a fixed order;
* :meth:`PureLoss.terms` computes the ``loss_*`` terms and the diagnostics from the loss's parameters (a flat
  ``name -> tensor`` dict, :meth:`PureLoss.term_parameters`) and those inputs, with the equation functions of
  the loss's module.

``forward`` calls ``terms(self.term_parameters(), self.inputs(tensordict))`` and writes what the loss produces
(a DICE dual's weights) back into the tensordict. The compiled and vectorised update steps
(:mod:`spoil_torchrl.trainers.compiled`) call the same two methods on every loss of a step, subclasses
included, and trace ``terms`` with ``torch.compile`` (Dynamo skips the frames that put functional parameters
in place with tensordict's ``to_module``, so the networks are called with :func:`torch.func.functional_call`).

Networks are read through :class:`PureNetwork` and :class:`PurePolicy`. A network they cannot call as a
function of plain tensors (not a single module wrapped in a :class:`~tensordict.nn.TensorDictModule`, or a
policy that is not such a network followed by a ``loc`` / ``scale`` distribution) is still evaluated, through
``to_module``, so the eager ``forward`` works with any network; only the compiled step refuses it
(:class:`NotCompilable`, and it trains eagerly).
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential, dispatch
from tensordict.utils import NestedKey
from torch import nn
from torch.func import functional_call
from torchrl.objectives import LossModule

from spoil_torchrl.objectives.keys import get_role

Tensors = dict[str, torch.Tensor]


class NotCompilable(Exception):
    """A loss (or one of its networks) has no form the compiled step can trace; the message says which and why."""


def flat_rows(role: TensorDictBase, key: NestedKey) -> torch.Tensor:
    """``role[key]`` with the role's batch dimensions flattened into one.

    Examples:
        >>> role = TensorDict({"observation": torch.zeros(2, 3, 4)}, [2, 3])
        >>> flat_rows(role, "observation").shape
        torch.Size([6, 4])
    """
    value = role.get(key)
    return value.reshape(-1, *value.shape[role.batch_dims :])


class PureNetwork:
    """A loss's functional network as a function of ``(parameters, *input tensors)``, inputs in ``in_keys``
    order, returning the network's outputs (a tuple when it writes several).

    ``params`` are the loss's own functional parameters of the network (``loss.<name>_params``); for a
    :class:`~tensordict.nn.TensorDictModule` around one module (what :mod:`spoil_torchrl.modules` builds) they
    are named as :func:`torch.func.functional_call` expects them for that module, and the call traces under
    ``torch.compile``. Any other network is evaluated through the tensordict it reads (eager only:
    :meth:`check_compilable` raises).
    """

    def __init__(self, network: nn.Module, params: TensorDictBase, what: str) -> None:
        self.what = what
        self.network = network
        self.in_keys = list(network.in_keys)
        self.out_keys = list(network.out_keys)
        flat = params.flatten_keys(".")
        self.plain = (  # a TensorDictSequential is a TensorDictModule too, but over modules that read tensordicts
            isinstance(network, TensorDictModule)
            and not isinstance(network, TensorDictSequential)
            and bool(self.in_keys)
            and all(key.startswith("module.") for key in flat.keys())
        )
        self.prefix = "module." if self.plain else ""

    def parameters(self, params: TensorDictBase) -> Tensors:
        """The network's parameters (``loss.<name>_params``) as the flat dict :meth:`__call__` takes."""
        return {key.removeprefix(self.prefix): value for key, value in params.flatten_keys(".").items()}

    def check_compilable(self) -> None:
        if not self.plain:
            raise NotCompilable(f"{self.what} is not one module wrapped in a TensorDictModule")

    @property
    def in_key(self) -> NestedKey:
        """The one input of a network of states (nu, chi)."""
        if len(self.in_keys) != 1:
            raise ValueError(
                f"{self.what} reads {len(self.in_keys)} entries {self.in_keys}; it must read one"
            )
        return self.in_keys[0]

    def __call__(self, params: Tensors, *xs: torch.Tensor):
        if self.plain:
            return functional_call(self.network.module, params, xs)
        td = TensorDict(dict(zip(self.in_keys, xs, strict=True)), [xs[0].shape[0]])
        with TensorDict(params).unflatten_keys(".").to_module(self.network):
            out = self.network(td)
        values = tuple(out.get(key) for key in self.out_keys)
        return values[0] if len(values) == 1 else values


class PurePolicy:
    """A loss's policy as :meth:`log_prob` of ``(parameters, states, actions)``, scored as the policy's
    distribution scores them (``actor.get_dist(states).log_prob(actions)``).

    The compiled step traces a policy of :func:`~spoil_torchrl.modules.make_actor` (a network writing ``loc``
    and ``scale`` followed by their distribution): its states are one tensor (:meth:`states`). Any other
    probabilistic actor is scored through ``get_dist`` on a tensordict of its inputs (eager only).
    """

    def __init__(self, actor: nn.Module, params: TensorDictBase, what: str) -> None:
        self.what = what
        self.actor = actor
        self.in_keys = list(actor.in_keys)
        modules = list(getattr(actor, "module", ()))
        dist_module = modules[-1] if modules else None
        self.plain = (
            len(modules) == 2
            and sorted(getattr(dist_module, "in_keys", [])) == ["loc", "scale"]
            and len(self.in_keys) == 1
            and list(getattr(modules[0], "out_keys", [])) == ["loc", "scale"]
        )
        if self.plain:
            self.net = PureNetwork(modules[0], params.get(("module", "0")), what)
            self.plain = self.net.plain
        if self.plain:
            self.distribution = dist_module.distribution_class
            self.distribution_kwargs = dict(dist_module.distribution_kwargs)

    def parameters(self, params: TensorDictBase) -> Tensors:
        """The policy's parameters (``loss.actor_network_params``) as the flat dict :meth:`log_prob` takes."""
        if self.plain:
            return self.net.parameters(params.get(("module", "0")))
        return dict(params.flatten_keys(".").items())

    def check_compilable(self) -> None:
        if not self.plain:
            raise NotCompilable(f"{self.what} is not a network followed by a loc/scale distribution")

    def states(self, role: TensorDictBase) -> torch.Tensor | TensorDictBase:
        """The policy's inputs in ``role``, rows flattened: a tensor, or a tensordict of its inputs."""
        if self.plain:
            return flat_rows(role, self.in_keys[0])
        return role.select(*self.in_keys).reshape(-1)

    def log_prob(self, params: Tensors, states, actions: torch.Tensor) -> torch.Tensor:
        if not self.plain:
            with TensorDict(params).unflatten_keys(".").to_module(self.actor):
                return self.actor.get_dist(states).log_prob(actions).reshape(-1)
        loc, scale = self.net(params, states)
        dist = self.distribution(loc=loc, scale=scale, **self.distribution_kwargs)
        return dist.log_prob(actions).reshape(-1)


class PureLoss(LossModule):
    """A LossModule whose ``forward`` is ``terms(term_parameters(), inputs(tensordict))`` (module docstring).

    A subclass implements:

    * :meth:`term_parameters`: the parameters its terms differentiate, ``name -> parameter``;
    * :meth:`inputs`: the batch's plain tensors (and random draws);
    * :meth:`terms`: ``(total, outputs)``, the sum of the ``loss_*`` terms and every output, from parameters
      and inputs; it may put detached tensors into ``produced`` (e.g. a DICE dual's weights at
      ``(role, "dice_weight")``), which a later loss of the same step reads instead of the tensordict;
    * :attr:`produces`: the keys it puts there, each with the role whose rows it holds;
    * :meth:`check_compilable`: raise :class:`NotCompilable` when a network cannot be traced.

    Examples:
        >>> from spoil_torchrl.modules import make_actor
        >>> from spoil_torchrl.objectives import WeightedBCLoss
        >>> loss = WeightedBCLoss(make_actor(3, 2, hidden_cells=(8,)), role="performant")
        >>> batch = TensorDict({"performant": TensorDict({"observation": torch.randn(4, 3),
        ...                                               "action": torch.zeros(4, 2)}, [4])}, [])
        >>> total, outputs = loss.terms(loss.term_parameters(), loss.inputs(batch), {})
        >>> bool(total == loss(batch)["loss_actor"])
        True
    """

    #: names of the functional parameter tensordicts ``forward`` clears TorchRL's weak references of
    functional_params: tuple[str, ...] = ()

    def term_parameters(self) -> dict[str, nn.Parameter]:
        raise NotImplementedError

    def _pure(self, name: str, make):
        """``make()`` (a :class:`PureNetwork` or :class:`PurePolicy` of this loss), made once and kept."""
        cache = self.__dict__.setdefault("_pure_networks", {})
        if name not in cache:
            cache[name] = make()
        return cache[name]

    def inputs(self, tensordict: TensorDictBase, produced: frozenset = frozenset()) -> Tensors:
        """The plain tensors :meth:`terms` reads from ``tensordict``; the keys in ``produced`` come from an
        earlier loss of the step and are not read."""
        raise NotImplementedError

    def terms(self, params: Tensors, x: Tensors, produced: dict) -> tuple[torch.Tensor, Tensors]:
        raise NotImplementedError

    @property
    def produces(self) -> dict[NestedKey, NestedKey]:
        """The keys :meth:`terms` puts into ``produced``, each mapped to the role whose rows it holds
        (default: none). ``forward`` writes them into the role, one value per row."""
        return {}

    def _rows_shape(self, tensordict: TensorDictBase, role: NestedKey) -> torch.Size:
        """The shape of ``role``'s rows, in which ``forward`` writes what the loss produces."""
        return get_role(tensordict, role).batch_size

    def check_compilable(self) -> None:
        """Raise :class:`NotCompilable` if the compiled step cannot trace :meth:`terms` (default: it can)."""

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The loss terms and diagnostics of ``tensordict``; what the loss produces is written into it."""
        produced: dict = {}
        _, outputs = self.terms(self.term_parameters(), self.inputs(tensordict), produced)
        with torch.no_grad():
            for key, role in self.produces.items():
                shape = self._rows_shape(tensordict, role)
                tensordict.set(key, produced[key].detach().reshape(*shape, 1))
        out = TensorDict(outputs, [])
        self._clear_weakrefs(tensordict, out, *self.functional_params)
        return out
