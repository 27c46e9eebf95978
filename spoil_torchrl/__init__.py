"""spoil_torchrl: offline imitation learning from safety-performance dual demonstrations on TorchRL.

The package implements SpoilDICE ("SpoilDICE: Safe and Performant Offline Imitation Learning from Dual
Demonstrations", ICLR 2026 submission; authors' code at https://anonymous.4open.science/r/iclr2026_spoildice-214C)
as composable TorchRL :class:`~torchrl.objectives.LossModule` s:

* :class:`~spoil_torchrl.objectives.PUDiscriminatorLoss` -- density-ratio discriminators (Eq. 16-18);
* :class:`~spoil_torchrl.objectives.SupportEstimator` -- the kappa-quantile safe-support indicator (Eq. 13);
* :class:`~spoil_torchrl.objectives.SpoilDICELoss` -- the DICE dual over (nu, lambda) (Eq. 11, 12, 19);
* :class:`~spoil_torchrl.objectives.WeightedBCLoss` -- weighted behavioural cloning (Eq. 20).

:mod:`spoil_torchrl.tabular` holds exact distribution-level solvers used to check the neural losses.
"""

__version__ = "0.1.0"

from spoil_torchrl.console import quiet_unrelated_notices

quiet_unrelated_notices()  # before anything imports gymnasium (see spoil_torchrl.console)
