"""Networks used by the losses: plain TorchRL / tensordict modules."""

from spoil_torchrl.modules.actor import ClippedTanhNormal, NormalParams, make_actor
from spoil_torchrl.modules.critics import make_discriminator, make_value_network
from spoil_torchrl.modules.normalization import (
    ObservationNormalizer,
    observation_normalizer_of,
    with_observation_norm,
)

__all__ = [
    "ClippedTanhNormal",
    "NormalParams",
    "ObservationNormalizer",
    "make_actor",
    "make_discriminator",
    "make_value_network",
    "observation_normalizer_of",
    "with_observation_norm",
]
