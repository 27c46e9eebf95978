"""Training loops: TorchRL Trainer glue for offline learning."""

from spoil_torchrl.stopping import stop_on_signals
from spoil_torchrl.trainers.compiled import CompiledStepper
from spoil_torchrl.trainers.fused_adam import FusedAdamSteps
from spoil_torchrl.trainers.offline import (
    MultiLossStepper,
    OfflineBatchSource,
    SampleBuffers,
    StepEvery,
    offline_trainer,
)

__all__ = [
    "CompiledStepper",
    "FusedAdamSteps",
    "MultiLossStepper",
    "OfflineBatchSource",
    "SampleBuffers",
    "StepEvery",
    "offline_trainer",
    "stop_on_signals",
]
