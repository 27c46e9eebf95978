"""Small main stages of every loss of the package, built the same way on every call: what the compiled and the
vectorised step tests step and compare with the eager step."""

from __future__ import annotations

import torch

from spoil_torchrl.modules import make_actor, make_discriminator, make_value_network
from spoil_torchrl.objectives import (
    COptiDICELoss,
    DemoDICELoss,
    DWBCLoss,
    PUDiscriminatorLoss,
    SafeDICELoss,
    SpoilDICELoss,
    WeightedBCLoss,
)
from spoil_torchrl.trainers import StepEvery
from tests.conftest import ACT_DIM, OBS_DIM

STEPS = 4


def sgd(params, lr: float = 1e-2) -> torch.optim.Optimizer:
    """The tests' optimiser. Not Adam: nu's constant offset is free in every DICE dual, so the gradient of nu's
    output bias is 0 up to float noise, which Adam's first steps scale to +/- lr whatever its size; any two
    correct implementations (or machines) then differ by lr in that bias. SGD keeps float noise as small as it
    is, so a few steps of two implementations can be compared to a tight tolerance."""
    return torch.optim.SGD(list(params), lr=lr)


def weighted_bc(role: str, weight: str = "dice_weight") -> WeightedBCLoss:
    """The policy extraction of the small main stages: a one-layer actor, weighted BC on ``role``."""
    return WeightedBCLoss(make_actor(OBS_DIM, ACT_DIM, hidden_cells=(32,)), role=role, weight=weight)


def spoildice(distribution: str, penalty: float, cells: tuple[int, ...] = (32, 32)):
    """SpoilDICE + weighted BC on its weights: the same initial weights on every call."""
    torch.manual_seed(3)
    dice = SpoilDICELoss(make_value_network(OBS_DIM, hidden_cells=cells), gradient_penalty=penalty)
    actor = WeightedBCLoss(
        make_actor(OBS_DIM, ACT_DIM, hidden_cells=cells, distribution=distribution),
        role="unlabeled",
        weight="dice_weight",
    )
    optimizers = [
        sgd(dice.nu_network_params.values(True, True)),
        sgd([dice.lagrange]),
        sgd(actor.parameters()),
    ]
    return {"dice": dice, "actor": actor}, optimizers


def demodice_s():
    """DemoDICE-S's main stage: nu on D_S with the reward log d_P/d_S, weighted BC on D_S."""
    torch.manual_seed(3)
    dice = DemoDICELoss(
        make_value_network(OBS_DIM, hidden_cells=(32, 32)),
        gradient_penalty=10.0,
        regularization="safe",
        reward="log_ratio_performant",
    )
    actor = weighted_bc("safe")
    optimizers = [sgd(dice.nu_network_params.values(True, True)), sgd(actor.parameters())]
    return {"dice": dice, "actor": actor}, optimizers


def discriminators():
    """Stage 1: C_P (gradient penalty 10) and C_S (none) against D_U, as the recipe pre-trains them."""
    torch.manual_seed(3)
    losses = {
        f"disc_{role}": PUDiscriminatorLoss(
            make_discriminator(OBS_DIM, ACT_DIM, hidden_cells=(32, 32)),
            positive=role,
            gradient_penalty=penalty,
        )
        for role, penalty in (("performant", 10.0), ("safe", 0.0))
    }
    return losses, [sgd(loss.parameters()) for loss in losses.values()]


def safedice():
    """SafeDICE's main stage (its logit read from an entry dual_batch has), weighted BC on D_U."""
    torch.manual_seed(3)
    dice = SafeDICELoss(make_value_network(OBS_DIM, hidden_cells=(32, 32)), alpha=0.5, gradient_penalty=10.0)
    dice.set_keys(logit="log_ratio_performant")
    actor = weighted_bc("unlabeled")
    optimizers = [sgd(dice.nu_network_params.values(True, True)), sgd(actor.parameters())]
    return {"dice": dice, "actor": actor}, optimizers


def dwbc():
    """DWBC: the policy and D(s, a, log pi) trained jointly, the discriminator's optimiser every 2nd step."""
    torch.manual_seed(3)
    loss = DWBCLoss(
        make_actor(OBS_DIM, ACT_DIM, hidden_cells=(32,)),
        make_discriminator(OBS_DIM, ACT_DIM, hidden_cells=(32,), extra_inputs={"policy_log_prob": 1}),
        alpha=7.5,
        eta=0.5,
    )
    optimizers = [
        sgd(loss.actor_network_params.values(True, True)),
        StepEvery(sgd(loss.discriminator_network_params.values(True, True)), 2),
    ]
    return {"dwbc": loss}, optimizers


def coptidice(cost_ub_epsilon: float):
    """COptiDICE's main stage (nu, chi, tau, lambda; chi off with cost_ub_epsilon=0), weighted BC on D_U."""
    torch.manual_seed(3)
    dice = COptiDICELoss(
        make_value_network(OBS_DIM, hidden_cells=(32,)),
        make_value_network(OBS_DIM, hidden_cells=(32,)),
        cost_limit=0.2,
        cost_ub_epsilon=cost_ub_epsilon,
        gradient_penalty=10.0,
    )
    actor = weighted_bc("unlabeled")
    return {"dice": dice, "actor": actor}, [sgd(dice.parameters()), sgd(actor.parameters())]


def filtered_bc():
    """Weighted BC with its weight read from the batch (filtered BC's ``safe_support`` on D_P)."""
    torch.manual_seed(3)
    actor = weighted_bc("performant", weight="safe_support")
    return {"actor": actor}, [sgd(actor.parameters())]


def run(stepper, batches):
    """``STEPS`` steps from a fixed random stream; the outputs, the parameters and the stream's state after."""
    torch.manual_seed(11)
    outputs = [stepper.step(None, batch.clone()) for batch in batches]
    return outputs, parameters_of(stepper.losses), torch.get_rng_state()


def parameters_of(losses) -> dict[str, torch.Tensor]:
    return {
        f"{name}.{key}": p.detach().clone()
        for name, loss in losses.items()
        for key, p in loss.named_parameters()
    }


def adam(losses, optimizers):
    """The same losses with the recipe's optimiser, Adam."""
    return losses, [torch.optim.Adam(o.param_groups[0]["params"], lr=1e-3) for o in optimizers]
