"""Training loops: TorchRL Trainer glue for offline learning."""

from spoil_torchrl.trainers.compiled import CompiledStepper, compile_stepper
from spoil_torchrl.trainers.offline import (
    MultiLossStepper,
    OfflineBatchSource,
    SampleBuffers,
    StepEvery,
    offline_trainer,
    stop_on_signals,
)

__all__ = [
    "CompiledStepper",
    "compile_stepper",
    "MultiLossStepper",
    "OfflineBatchSource",
    "SampleBuffers",
    "StepEvery",
    "offline_trainer",
    "stop_on_signals",
]
