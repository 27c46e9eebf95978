"""TorchRL loss modules of SpoilDICE, one concept per file."""

from spoil_torchrl.objectives.annotate import annotate
from spoil_torchrl.objectives.discriminator import (
    LogRatio,
    PUDiscriminatorLoss,
    logistic_ratio_losses,
    nnpu_risks,
    pu_log_ratio,
)
from spoil_torchrl.objectives.spoildice import (
    SpoilDICELoss,
    bellman_backup,
    closed_form_log_weight,
    spoildice_advantage,
    spoildice_dual,
)
from spoil_torchrl.objectives.support import SupportEstimator, quantile_threshold, support_indicator
from spoil_torchrl.objectives.weighted_bc import WeightedBCLoss, weighted_nll

__all__ = [
    "LogRatio",
    "PUDiscriminatorLoss",
    "SpoilDICELoss",
    "SupportEstimator",
    "WeightedBCLoss",
    "annotate",
    "bellman_backup",
    "closed_form_log_weight",
    "logistic_ratio_losses",
    "nnpu_risks",
    "pu_log_ratio",
    "quantile_threshold",
    "spoildice_advantage",
    "spoildice_dual",
    "support_indicator",
    "weighted_nll",
]
