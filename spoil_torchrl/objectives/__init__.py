"""TorchRL loss modules of SpoilDICE, one concept per file."""

from spoil_torchrl.objectives.annotate import annotate
from spoil_torchrl.objectives.coptidice import COptiDICELoss
from spoil_torchrl.objectives.coptidice_equations import (
    coptidice_dual,
    coptidice_log_weight,
    coptidice_weight,
    cost_bound_objective,
    cost_flow_residual,
    per_step_cost_limit,
    soft_chi2,
    worst_case_weights,
)
from spoil_torchrl.objectives.demodice import DemoDICELoss, demodice_dual, demodice_log_weight
from spoil_torchrl.objectives.discriminator import (
    LogRatio,
    PUDiscriminatorLoss,
    logistic_ratio_losses,
    nnpu_risks,
    pu_log_ratio,
)
from spoil_torchrl.objectives.dwbc import (
    DWBCLoss,
    dwbc_discriminator_loss,
    dwbc_expert_weight,
    dwbc_probability,
    dwbc_unlabeled_weight,
    log_prob_feature,
)
from spoil_torchrl.objectives.functional import bellman_backup, dice_advantage
from spoil_torchrl.objectives.safedice import (
    SafeDICELoss,
    safedice_auto_alpha,
    safedice_dual,
    safedice_log_weight,
    safedice_reward,
)
from spoil_torchrl.objectives.spoildice import (
    SpoilDICELoss,
    closed_form_log_weight,
    spoildice_advantage,
    spoildice_dual,
)
from spoil_torchrl.objectives.support import SupportEstimator, quantile_threshold, support_indicator
from spoil_torchrl.objectives.weighted_bc import WeightedBCLoss, weighted_nll

__all__ = [
    "COptiDICELoss",
    "DWBCLoss",
    "DemoDICELoss",
    "LogRatio",
    "PUDiscriminatorLoss",
    "SafeDICELoss",
    "SpoilDICELoss",
    "SupportEstimator",
    "WeightedBCLoss",
    "annotate",
    "bellman_backup",
    "closed_form_log_weight",
    "coptidice_dual",
    "coptidice_log_weight",
    "coptidice_weight",
    "cost_bound_objective",
    "cost_flow_residual",
    "demodice_dual",
    "demodice_log_weight",
    "dice_advantage",
    "dwbc_discriminator_loss",
    "dwbc_expert_weight",
    "dwbc_probability",
    "dwbc_unlabeled_weight",
    "log_prob_feature",
    "logistic_ratio_losses",
    "nnpu_risks",
    "per_step_cost_limit",
    "pu_log_ratio",
    "quantile_threshold",
    "safedice_auto_alpha",
    "safedice_dual",
    "safedice_log_weight",
    "safedice_reward",
    "soft_chi2",
    "spoildice_advantage",
    "spoildice_dual",
    "support_indicator",
    "weighted_nll",
    "worst_case_weights",
]
