"""What every algorithm shares: the run's :class:`BuildContext`, the two stages an :class:`Algorithm` is made
of (a pre-training that returns an immutable :class:`Pretraining`, a main stage that builds the
:class:`PolicyTraining` from it), and the pieces several of them assemble from (the actor, Adam, a weighted-BC
main stage, a DICE main stage). The PU discriminators of stage 1 and the support cut of Eq. 13 are in
:mod:`~spoil_torchrl.algorithms.discriminators`."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import torch
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import LossModule

from spoil_torchrl.data.buffers import DualDemoBuffers
from spoil_torchrl.modules import ObservationNormalizer, make_actor, with_observation_norm
from spoil_torchrl.objectives import WeightedBCLoss
from spoil_torchrl.trainers.offline import MultiLossStepper


@dataclass(frozen=True)
class EpisodeConstraint:
    """The run's safety constraint as the evaluation sees it: episodes of at most ``episode_length`` steps (the
    task's time limit T) whose summed cost should stay within ``cost_threshold`` (the prepared dataset's).

    Examples:
        >>> from spoil_torchrl.tasks import get_env_task
        >>> task = get_env_task("SafetyPointCircle1-v0")
        >>> constraint = EpisodeConstraint(cost_threshold=25.0, episode_length=task.episode_length)
        >>> constraint
        EpisodeConstraint(cost_threshold=25.0, episode_length=500)
        >>> constraint.cost_threshold / constraint.episode_length  # the mean cost per step it allows
        0.05

    It reaches the builders that need it (COptiDICE, FBC's oracle ablation) as
    ``BuildContext(..., constraint=constraint)``.
    """

    cost_threshold: float
    episode_length: int


@dataclass
class BuildContext:
    """What a builder reads besides its own settings: the run's data and how to report.

    Attributes:
        buffers: D_S, D_P, D_U (and any extra role) and the initial states, one replay buffer each.
        observation_dim: the size of a (standardised) observation.
        action_dim: the size of an action.
        constraint: the dataset's episode-cost threshold and the task's horizon (read by FBC's oracle ablation
            and COptiDICE only).
        logger: the TorchRL logger pre-training logs into (``None``: no log rows, e.g. a resumed run).
        progress: whether pre-training shows a progress bar.
        device: where the losses (networks, their parameters, and so the optimisers' states) live: the
            buffers' device (:mod:`spoil_torchrl.devices`). Every builder puts each loss there with
            :meth:`place` before it makes the loss's optimisers.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from spoil_torchrl.algorithms import ALGORITHMS, BuildContext
        >>> from spoil_torchrl.data import DualDemoBuffers
        >>> episodes = TensorDict({"observation": torch.randn(4, 3), "episode": torch.tensor([0, 0, 1, 1]),
        ...                        "is_init": torch.tensor([[True], [False], [True], [False]])}, [4])
        >>> buffers = DualDemoBuffers(episodes, {"performant": [1], "unlabeled": [0, 1]}, batch_size=2)
        >>> context = BuildContext(buffers, observation_dim=3, action_dim=2, progress=False)
        >>> training = ALGORITHMS["bc"]({"distribution": "normal", "hidden_cells": [16], "actor_lr": 1e-3}, context)
        >>> sorted(training.stepper.losses)
        ['actor']
    """

    buffers: DualDemoBuffers
    observation_dim: int
    action_dim: int
    constraint: EpisodeConstraint | None = None
    logger: Any = None
    progress: bool = True
    device: torch.device = torch.device("cpu")

    def place(self, loss: LossModule) -> LossModule:
        """``loss`` (its networks, parameters and buffers) moved to :attr:`device`; returns it."""
        return loss.to(self.device)


@dataclass
class PolicyTraining:
    """What the recipe trains in its main stage.

    Attributes:
        stepper: the optimisation step (losses in order, their optimisers and schedules).
        policy_loss: the loss holding the policy (``actor_network`` / ``actor_network_params``).
        diagnostics: extra numbers measured before the main stage (e.g. the support share of D_U).
        dice: the DICE loss of the main stage, if any (it writes ``dice_weight`` / ``dice_advantage`` into
            ``dice_role``'s transitions; :func:`~spoil_torchrl.eval.dice_diagnostics.dice_diagnostics` reads it).
        dice_role: the role the DICE loss weights (D_U, or D_S for DemoDICE-S).
        observation_norm: the statistics the training data were standardised with, if any.

    Examples:
        >>> from tensordict import TensorDict
        >>> from spoil_torchrl.data import DualDemoBuffers
        >>> episodes = TensorDict({"observation": torch.randn(8, 3), "action": torch.rand(8, 2) * 2 - 1,
        ...                        "episode": torch.arange(4).repeat_interleave(2),
        ...                        "is_init": torch.tensor([[True], [False]] * 4)}, [8])
        >>> roles = {"safe": [0, 1], "performant": [1, 2], "unlabeled": [0, 1, 2, 3]}
        >>> buffers = DualDemoBuffers(episodes, roles, batch_size=4)
        >>> context = BuildContext(buffers, observation_dim=3, action_dim=2, progress=False)
        >>> from spoil_torchrl.algorithms import ALGORITHMS
        >>> cfg = {"distribution": "normal", "hidden_cells": [16], "actor_lr": 1e-3}
        >>> training = ALGORITHMS["bc"](cfg, context)
        >>> from spoil_torchrl.trainers import offline_trainer
        >>> trainer = offline_trainer(training.stepper, buffers.sample, total_steps=3, progress_bar=False)
        >>> trainer.train()
        >>> with training.policy() as policy:  # the trained policy, as a plain module
        ...     action = policy(TensorDict({"observation": torch.zeros(5, 3)}, [5]))["action"]
        >>> action.shape, training.dice is None, training.diagnostics
        (torch.Size([5, 2]), True, {})
    """

    stepper: MultiLossStepper
    policy_loss: LossModule
    diagnostics: dict[str, float]
    dice: LossModule | None = None
    dice_role: str | None = None
    observation_norm: ObservationNormalizer | None = None

    @contextlib.contextmanager
    def policy(self) -> Iterator[ProbabilisticActor]:
        """The current policy as a plain module (the loss's functional parameters put in place). When the
        training data were standardised (``observation_norm``), the policy standardises raw observations
        itself, so it can act in the environment and be saved as one self-contained file."""
        loss = self.policy_loss
        with loss.actor_network_params.to_module(loss.actor_network):
            if self.observation_norm is None:
                yield loss.actor_network
            else:
                yield with_observation_norm(loss.actor_network, self.observation_norm)


def _read_only(mapping: Mapping) -> Mapping:
    return MappingProxyType({k: _read_only(v) if isinstance(v, Mapping) else v for k, v in mapping.items()})


@dataclass(frozen=True)
class Pretraining:
    """What an algorithm's pre-training stage returns (stage 1 of Algorithm 1), and all the main stage reads of
    it: a value a run can store and a resumed run load instead of training the discriminators again.

    Attributes:
        annotations: role -> key -> the values the stage wrote into that role's stored transitions, one row per
            transition in storage order (SpoilDICE: ``log_ratio_performant`` and ``safe_support`` on D_U).
        diagnostics: the numbers the stage measured (support share, threshold, SafeDICE's alpha ...); the main
            stage may read them.
        networks: name -> state dict of each frozen network the stage trained (C_P, C_S), for inspection; the
            main stage reads only the annotations they made.

    The mappings are read-only. An algorithm without a pre-training returns :data:`NO_PRETRAINING`.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from spoil_torchrl.data import DualDemoBuffers
        >>> episodes = TensorDict({"observation": torch.arange(4.0).unsqueeze(-1),
        ...                        "episode": torch.tensor([0, 0, 1, 1]),
        ...                        "is_init": torch.tensor([[True], [False], [True], [False]])}, [4])
        >>> buffers = DualDemoBuffers(episodes, {"unlabeled": [0, 1]}, batch_size=2)
        >>> buffers.annotate("unlabeled", "score", lambda td: 2 * td["observation"])
        >>> stage = Pretraining.of(buffers, {"unlabeled": ["score"]}, {"mean_score": 3.0})
        >>> fresh = DualDemoBuffers(episodes.exclude("score"), {"unlabeled": [0, 1]}, batch_size=2)
        >>> stage.apply(fresh)  # a resumed run: the stored annotations, no training
        >>> fresh["unlabeled"].storage[:]["score"].squeeze(-1).tolist()
        [0.0, 2.0, 4.0, 6.0]
    """

    annotations: Mapping[str, Mapping[str, torch.Tensor]] = field(default_factory=dict)
    diagnostics: Mapping[str, float] = field(default_factory=dict)
    networks: Mapping[str, Mapping[str, torch.Tensor]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("annotations", "diagnostics", "networks"):
            object.__setattr__(self, name, _read_only(getattr(self, name)))

    @classmethod
    def of(
        cls,
        buffers: DualDemoBuffers,
        keys: Mapping[str, Sequence[str]],
        diagnostics: Mapping[str, float],
        networks: Mapping[str, torch.nn.Module] | None = None,
    ) -> Pretraining:
        """The stage's value once it has annotated ``buffers``: a copy of each role's annotated ``keys``, the
        ``diagnostics`` and the state dicts of ``networks``."""
        annotations = {
            role: {key: buffers[role].storage[:][key].clone() for key in role_keys}
            for role, role_keys in keys.items()
        }
        states = {
            name: {k: v.detach().clone() for k, v in module.state_dict().items()}
            for name, module in (networks or {}).items()
        }
        return cls(annotations, dict(diagnostics), states)

    def apply(self, buffers: DualDemoBuffers) -> None:
        """Write the stored annotations into ``buffers`` (a resumed run's, loaded from the same data)."""
        for role, values in self.annotations.items():
            for key, value in values.items():
                buffers.set_annotation(role, key, value)

    def as_state(self) -> dict:
        """Plain dicts of tensors and numbers (what ``torch.save(weights_only=True)`` stores)."""
        plain = lambda m: {k: plain(v) if isinstance(v, Mapping) else v for k, v in m.items()}  # noqa: E731
        return {name: plain(getattr(self, name)) for name in ("annotations", "diagnostics", "networks")}


#: The value of an algorithm that pre-trains nothing (BC, DWBC-S, COptiDICE).
NO_PRETRAINING = Pretraining()


def no_pretraining(cfg: Mapping[str, Any], context: BuildContext) -> Pretraining:
    """The pre-training stage of an algorithm that has none.

    Examples:
        >>> from spoil_torchrl.algorithms import ALGORITHMS
        >>> [name for name, algorithm in ALGORITHMS.items() if algorithm.pretrain is no_pretraining]
        ['bc', 'dwbc_s', 'coptidice']
        >>> no_pretraining({}, context=None) is NO_PRETRAINING  # nothing to annotate, store or load
        True
    """
    return NO_PRETRAINING


@dataclass(frozen=True)
class Algorithm:
    """An algorithm of the main recipe as its two stages.

    Attributes:
        pretrain: ``(cfg, context) -> Pretraining``: everything before the policy is trained (SpoilDICE: C_P,
            C_S, the support cut, D_U annotated once); it writes its annotations into ``context.buffers`` and
            returns them with its diagnostics.
        main: ``(cfg, context, pretraining) -> PolicyTraining``: the main stage's losses and optimisers, built
            on buffers that hold ``pretraining``'s annotations.

    Calling the algorithm runs both, as a fresh run does: ``algorithm(cfg, context)``.

    Examples:
        >>> from tensordict import TensorDict
        >>> from spoil_torchrl.data import DualDemoBuffers
        >>> episodes = TensorDict({"observation": torch.randn(8, 3), "action": torch.rand(8, 2) * 2 - 1,
        ...                        "episode": torch.arange(4).repeat_interleave(2),
        ...                        "is_init": torch.tensor([[True], [False]] * 4)}, [8])
        >>> roles = {"safe": [0, 1], "performant": [1, 2], "unlabeled": [0, 1, 2, 3]}
        >>> buffers = DualDemoBuffers(episodes, roles, batch_size=4)
        >>> context = BuildContext(buffers, observation_dim=3, action_dim=2, progress=False)
        >>> from spoil_torchrl.algorithms.imitation import build_bc
        >>> bc = Algorithm(no_pretraining, build_bc)  # as ALGORITHMS["bc"]
        >>> cfg = {"distribution": "normal", "hidden_cells": [16], "actor_lr": 1e-3}
        >>> stage = bc.pretrain(cfg, context)  # a run stores it; a resumed run loads it instead
        >>> training = bc.main(cfg, context, stage)
        >>> stage is NO_PRETRAINING, sorted(training.stepper.losses)
        (True, ['actor'])
        >>> sorted(bc(cfg, context).stepper.losses)  # both stages at once
        ['actor']
    """

    pretrain: Callable[[Mapping[str, Any], BuildContext], Pretraining]
    main: Callable[[Mapping[str, Any], BuildContext, Pretraining], PolicyTraining]

    def __call__(self, cfg: Mapping[str, Any], context: BuildContext) -> PolicyTraining:
        return self.main(cfg, context, self.pretrain(cfg, context))


def actor(cfg: Mapping[str, Any], context: BuildContext) -> ProbabilisticActor:
    """The policy network of ``cfg`` (``hidden_cells``, ``distribution``) for the context's sizes."""
    return make_actor(
        context.observation_dim,
        context.action_dim,
        hidden_cells=tuple(cfg["hidden_cells"]),
        distribution=cfg["distribution"],
    )


def adam(params, lr: float) -> torch.optim.Adam:
    """Adam over ``params`` (every optimiser of the recipe's algorithms)."""
    return torch.optim.Adam(list(params), lr=float(lr))


def weighted_bc_stage(
    cfg: Mapping[str, Any], context: BuildContext, role: str, weight: str | None, diagnostics: dict
) -> PolicyTraining:
    """A main stage of weighted BC alone (Eq. 20 on ``role`` with ``weight``): BC, FBC, JFBC."""
    policy_loss = context.place(WeightedBCLoss(actor(cfg, context), role=role, weight=weight))
    stepper = MultiLossStepper({"actor": policy_loss}, [adam(policy_loss.parameters(), cfg["actor_lr"])])
    return PolicyTraining(stepper, policy_loss, diagnostics)


def dice_stage(
    cfg: Mapping[str, Any],
    context: BuildContext,
    dice: LossModule,
    dual_optimizers: list[torch.optim.Optimizer],
    role: str,
    diagnostics: dict,
) -> PolicyTraining:
    """A DICE main stage: ``dice`` writes ``dice_weight`` into ``role`` and pi is weighted BC on it (Eq. 20);
    the dual's optimisers step first, then the actor's."""
    policy_loss = context.place(WeightedBCLoss(actor(cfg, context), role=role, weight="dice_weight"))
    optimizers = [*dual_optimizers, adam(policy_loss.parameters(), cfg["actor_lr"])]
    stepper = MultiLossStepper({"dice": dice, "actor": policy_loss}, optimizers)
    return PolicyTraining(stepper, policy_loss, diagnostics, dice=dice, dice_role=role)
