"""Networks used by the losses: plain TorchRL / tensordict modules."""

from spoil_torchrl.modules.actor import ClippedTanhNormal, NormalParams, make_actor
from spoil_torchrl.modules.critics import make_discriminator, make_value_network

__all__ = ["ClippedTanhNormal", "NormalParams", "make_actor", "make_discriminator", "make_value_network"]
