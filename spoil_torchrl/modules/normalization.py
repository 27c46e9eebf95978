"""Observation standardisation: statistics fitted once on offline data, and the module that applies them.

Every network of the DSRL recipe reads *standardised* states: the recipe standardises the dataset once
(:func:`spoil_torchrl.data.standardize_observations`), so that gradient penalties act on states of unit scale,
and the policy it saves carries an :class:`ObservationNormalizer` in front of its MLP
(:func:`with_observation_norm`), so that a loaded policy acting on raw environment observations standardises
them itself.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import ProbabilisticActor

#: Added to the standard deviation (the DICE reference codes' ``1 / (std + 1e-3)`` scale), so that a constant
#: observation dimension is shifted but not blown up.
STD_EPS = 1e-3


class ObservationNormalizer(nn.Module):
    """``(x - loc) / scale`` with ``loc`` and ``scale`` stored as buffers (saved in the state dict).

    Args:
        loc: per-dimension shift (the data mean).
        scale: per-dimension scale (the data standard deviation plus :data:`STD_EPS`); must be positive.

    Examples:
        >>> norm = ObservationNormalizer.from_observations(torch.tensor([[0.0, 10.0], [2.0, 10.0]]))
        >>> norm.loc.tolist(), [round(s, 3) for s in norm.scale.tolist()]
        ([1.0, 10.0], [1.001, 0.001])
        >>> [round(x, 4) for x in norm(torch.tensor([[2.0, 10.0]]))[0].tolist()]
        [0.999, 0.0]
    """

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor) -> None:
        super().__init__()
        loc = torch.as_tensor(loc, dtype=torch.float32).reshape(-1)
        scale = torch.as_tensor(scale, dtype=torch.float32).reshape(-1)
        if loc.shape != scale.shape:
            raise ValueError(
                f"loc and scale must have the same shape, got {tuple(loc.shape)} and {tuple(scale.shape)}"
            )
        self.register_buffer("loc", loc)
        self.register_buffer("scale", scale)
        self.validate()

    def validate(self) -> None:
        """Raise ``ValueError`` unless ``loc`` is finite and ``scale`` finite and positive (also after loading a
        state dict, which bypasses the constructor's check)."""
        finite = torch.isfinite(self.loc).all() & torch.isfinite(self.scale).all()
        if not bool(finite) or bool((self.scale <= 0).any()):
            raise ValueError("loc must be finite and scale finite and positive")

    @classmethod
    def from_observations(cls, observations: torch.Tensor, eps: float = STD_EPS) -> ObservationNormalizer:
        """Mean and (population) standard deviation + ``eps`` of ``observations`` (``[N, dim]``)."""
        observations = torch.as_tensor(observations).reshape(-1, observations.shape[-1]).double()
        if observations.shape[0] == 0:
            raise ValueError("cannot fit observation statistics on no observations")
        loc = observations.mean(0)
        scale = observations.std(0, unbiased=False) + eps
        return cls(loc.float(), scale.float())

    @classmethod
    def identity(cls, dim: int) -> ObservationNormalizer:
        """A normaliser that changes nothing (shift 0, scale 1), e.g. to load a saved one into."""
        return cls(torch.zeros(dim), torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.loc) / self.scale

    def extra_repr(self) -> str:
        return f"dim={self.loc.numel()}"


def with_observation_norm(actor: ProbabilisticActor, normalizer: ObservationNormalizer) -> ProbabilisticActor:
    """A policy that standardises its observation with ``normalizer`` and then runs ``actor``.

    The result shares ``actor``'s layers (training one trains the other) and puts the normaliser first in
    its MLP, so its state dict (and a policy file written by :func:`~spoil_torchrl.zoo.save_policy`)
    holds the statistics next to the weights.

    Examples:
        >>> from tensordict import TensorDict
        >>> from spoil_torchrl.modules import make_actor
        >>> actor = make_actor(2, 1, hidden_cells=(4,), distribution="normal")
        >>> norm = ObservationNormalizer(torch.tensor([1.0, 2.0]), torch.tensor([2.0, 4.0]))
        >>> policy = with_observation_norm(actor, norm)
        >>> raw = torch.tensor([[3.0, 6.0]])
        >>> a = policy(TensorDict({"observation": raw}, [1]))["loc"]
        >>> b = actor(TensorDict({"observation": norm(raw)}, [1]))["loc"]
        >>> bool(torch.equal(a, b))
        True
    """
    inner, head = actor.module[0], actor.module[-1]
    if isinstance(inner.module[0], ObservationNormalizer):
        raise ValueError("this actor already standardises its observations")
    module = TensorDictModule(
        nn.Sequential(normalizer, *inner.module), in_keys=inner.in_keys, out_keys=inner.out_keys
    )
    return ProbabilisticActor(
        module,
        in_keys=head.in_keys,
        out_keys=head.dist_sample_keys,  # (the log-probability key, if any, follows from return_log_prob)
        distribution_class=head.distribution_class,
        distribution_kwargs=head.distribution_kwargs,
        return_log_prob=head.return_log_prob,
        default_interaction_type=head.default_interaction_type,
    )


def observation_normalizer_of(actor: ProbabilisticActor) -> ObservationNormalizer | None:
    """The :class:`ObservationNormalizer` inside ``actor`` (see :func:`with_observation_norm`), or ``None``.

    Examples:
        >>> from spoil_torchrl.modules import make_actor
        >>> actor = make_actor(2, 1, hidden_cells=(4,))
        >>> observation_normalizer_of(actor) is None  # reads its observations as they come
        True
        >>> norm = ObservationNormalizer(torch.tensor([1.0, 2.0]), torch.tensor([2.0, 4.0]))
        >>> found = observation_normalizer_of(with_observation_norm(actor, norm))
        >>> found is norm, found.loc.tolist()
        (True, [1.0, 2.0])
    """
    first = actor.module[0].module
    if isinstance(first, nn.Sequential) and isinstance(first[0], ObservationNormalizer):
        return first[0]
    return None
