"""Where a run trains: the ``device`` setting of the main recipe.

``device=cpu`` (the default) or ``device=cuda`` (``cuda:1`` for another GPU) places everything a run's training
holds on that device: the role buffers and their sampling generators (:class:`~spoil_torchrl.data.DualDemoBuffers`),
every network, loss parameter and optimiser state, the annotations the pre-training writes, the diagnostics'
fixed subsamples, the observation statistics and the policy that is evaluated. Indices are drawn on the device
by its own generator, so a training step neither moves data to the device nor reads a value back from it; the
main stage reads the losses back once per chunk of steps (at most 100), to log them and to stop a run that
diverged. The simulator runs on the CPU: an evaluation moves each observation to the device and each action
back (:func:`~spoil_torchrl.envs.rollout.rollout`). Seeds of a ``seeds=[...]`` run are then evaluated one after
another in the main process, since a CUDA policy cannot be handed to a forked worker.

A run on ``cuda`` draws its initial weights and batches from CUDA's generators, so its numbers differ from a
CPU run's with the same seed; a run on ``cpu`` is the run every committed result is.
"""

from __future__ import annotations

import torch

from spoil_torchrl.errors import SettingsError

#: The device a run without the setting trains on (every run before it existed).
DEFAULT_DEVICE = "cpu"


def training_device(name: str | torch.device | None) -> torch.device:
    """The device ``name`` names, checked to exist on this machine (``None``: :data:`DEFAULT_DEVICE`).

    Raises :class:`~spoil_torchrl.errors.SettingsError` for a name torch does not know, a device type other
    than CPU or CUDA, or a CUDA device this machine does not have.

    Examples:
        >>> training_device("cpu")
        device(type='cpu')
        >>> training_device("gpu")
        Traceback (most recent call last):
        ...
        spoil_torchrl.errors.SettingsError: device = 'gpu': expected cpu or cuda (cuda:<index> for one GPU of several)
    """
    expected = "expected cpu or cuda (cuda:<index> for one GPU of several)"
    try:
        device = torch.device(DEFAULT_DEVICE if name is None else name)
    except (RuntimeError, TypeError):
        raise SettingsError(f"device = {name!r}: {expected}") from None
    if device.type not in ("cpu", "cuda"):
        raise SettingsError(f"device = {name!r}: {expected}")
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise SettingsError(
                f"device = {name!r}: this machine has no CUDA device (torch {torch.__version__}, "
                f"CUDA build: {torch.version.cuda or 'none'}); train on device=cpu, or install a CUDA build of "
                "torch (make setup TORCH_SPEC=...)"
            )
        if device.index is not None and device.index >= count:
            raise SettingsError(
                f"device = {name!r}: this machine has {count} CUDA device(s), cuda:0 to cuda:{count - 1}"
            )
    return device
