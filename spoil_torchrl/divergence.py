"""A run that diverged stops, and says where: NaN or infinite losses, weights or actions are never trained on,
evaluated or reported.

A diverged policy is dangerous to report: its NaN actions make MuJoCo reset the simulation at every step, so
its episodes collect no cost and look perfectly safe. :func:`check_finite` is the one test every stage applies
(the main stage's losses at every chunk, the networks' weights before an evaluation, the policy's actions in a
rollout, an expert's PPO losses), and :class:`TrainingDiverged` the one error it raises: the recipes mark the run
``failed``, print its one line and exit non-zero, and the report skips failed runs.
"""

from __future__ import annotations

import torch


class TrainingDiverged(RuntimeError):
    """A loss, a weight or an action became NaN or infinite."""


def check_finite(what: str, value, where: str, advice: str = "") -> None:
    """Raise :class:`TrainingDiverged` naming ``what`` and ``where`` unless every entry of ``value`` (a tensor,
    array or number) is finite.

    Examples:
        >>> check_finite("loss bc.loss_actor", torch.tensor(1.5), "step 100")
        >>> check_finite("loss bc.loss_actor", torch.tensor(float("nan")), "step 100")
        Traceback (most recent call last):
        ...
        spoil_torchrl.divergence.TrainingDiverged: step 100: loss bc.loss_actor is not finite (nan)
    """
    tensor = torch.as_tensor(value)
    if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
        bad = tensor[~torch.isfinite(tensor)].reshape(-1)[0].item()
        raise TrainingDiverged(f"{where}: {what} is not finite ({bad}){'; ' + advice if advice else ''}")
