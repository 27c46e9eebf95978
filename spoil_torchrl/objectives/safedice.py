"""The SafeDICE dual over nu (Jang et al., 2023): imitation from unlabeled data and non-preferred (unsafe)
demonstrations, the SafeDICE baseline of the paper's section 5."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey

from spoil_torchrl.objectives.dice import DICELoss
from spoil_torchrl.objectives.functional import (
    bellman_backup,
    dice_advantage,
    log_mean_exp,
    self_normalized_weights,
    weight_diagnostics,
)
from spoil_torchrl.objectives.keys import get_role, role_entry
from spoil_torchrl.objectives.pure import Tensors
from spoil_torchrl.objectives.spoildice import closed_form_log_weight

#: Smallest argument of the reward's logarithm (the reference code's clip in its reward statistics).
REWARD_LOG_FLOOR = 1e-10


def safedice_reward(probability: torch.Tensor, alpha: float) -> torch.Tensor:
    """SafeDICE's reward :math:`r = \\log \\frac{1 - (1+\\alpha) D}{(1-\\alpha)(1-D)} = \\log \\frac{d_P}{d_U}`.

    :math:`D = d_N / (d_N + d_U)` is the probability of the non-preferred-vs-unlabeled discriminator (the
    sigmoid of its logit, Eq. 18's :math:`C`), so :math:`d_N/d_U = D/(1-D)`, and the mixture assumption
    :math:`d_U = \\alpha d_N + (1-\\alpha) d_P` gives :math:`d_P/d_U = (1 - \\alpha\\, d_N/d_U)/(1-\\alpha)`,
    which is the expression above.

    **Guard.** The mixture is only consistent where :math:`\\alpha d_N \\le d_U`, i.e. :math:`D \\le 1/(1+\\alpha)`;
    beyond it (a fixed :math:`\\alpha` too large for some samples, or a discriminator more confident on new data
    than on the data :func:`safedice_auto_alpha` saw) the log's argument is :math:`\\le 0` and the reference code
    returns NaN. We clip :math:`D` to at most :math:`1/(1+\\alpha)` and the numerator to at least
    ``REWARD_LOG_FLOOR`` (:math:`10^{-10}`, the reference's clip in its reward statistics): such samples get the
    lowest reward, :math:`\\log 10^{-10} - \\log(1-\\alpha) - \\log(\\alpha/(1+\\alpha))`, i.e. :math:`d_P = 0`
    up to the floor. Clipping :math:`D` (not only the numerator) keeps the reward non-increasing in :math:`D`:
    with the numerator floored alone, :math:`D \\to 1` would send the denominator to 0 and the reward to
    :math:`+\\infty`.

    Args:
        probability: :math:`D \\in [0, 1]`.
        alpha: the share :math:`\\alpha \\in [0, 1)` of non-preferred data in :math:`d_U`; 0 gives :math:`r = 0`.

    Examples:
        >>> d_n, d_p, alpha = torch.tensor([0.2, 0.0]), torch.tensor([0.0, 0.5]), 0.5
        >>> d_u = alpha * d_n + (1 - alpha) * d_p
        >>> D = d_n / (d_n + d_u)
        >>> [round(x, 6) for x in safedice_reward(D, alpha).exp().tolist()]  # d_P / d_U (0 up to the floor)
        [0.0, 2.0]
    """
    if not 0.0 <= alpha < 1.0:
        raise ValueError(f"alpha must lie in [0, 1), got {alpha}")
    if alpha == 0.0:  # d_P = d_U; the formula's 0/0 at D = 1 must not leak out
        return torch.zeros_like(probability)
    d = probability.clamp(0.0, 1.0 / (1.0 + alpha))
    numerator = (1.0 - (1.0 + alpha) * d).clamp_min(REWARD_LOG_FLOOR)
    return torch.log(numerator) - torch.log1p(-d) - math.log1p(-alpha)


def safedice_auto_alpha(probability: torch.Tensor, margin: float = 1e-5) -> float:
    """SafeDICE's "auto" :math:`\\alpha`: the largest share of :math:`d_N` in :math:`d_U` the discriminator allows,
    :math:`\\min(1, \\min_U (1-D)/D) - 10^{-5}`, floored at 0.

    :math:`\\alpha d_N \\le d_U` must hold on every unlabeled sample, i.e. :math:`\\alpha \\le (1-D)/D`
    (:func:`safedice_reward`). As in the reference code (``find_alpha``: the minimum starts at 1, then the
    margin is subtracted) the cap 1 comes before the margin, so :math:`\\alpha < 1` and :math:`1-\\alpha > 0`.
    The floor at 0 (not in the reference) keeps :math:`\\alpha` valid when some unlabeled sample has
    :math:`D > 1/(1 + 10^{-5})`; then the reward is 0 and SafeDICE is BC on :math:`D_U`.

    Args:
        probability: :math:`D` on (all) the unlabeled data.
        margin: subtracted after the minimum. Default :math:`10^{-5}` (reference).

    Examples:
        >>> round(safedice_auto_alpha(torch.tensor([0.1, 0.2, 0.6])), 6)  # (1 - 0.6) / 0.6 = 0.667
        0.666657
        >>> round(safedice_auto_alpha(torch.tensor([0.1, 0.2])), 6)  # capped at 1
        0.99999
    """
    if probability.numel() == 0:
        raise ValueError("safedice_auto_alpha needs at least one probability")
    d = probability.detach().double().clamp(0.0, 1.0)
    ratio = torch.where(d > 0, (1.0 - d) / d, torch.full_like(d, math.inf))
    return max(0.0, min(1.0, float(ratio.min())) - margin)


def safedice_dual(init_nu: torch.Tensor, advantage: torch.Tensor, gamma: float) -> torch.Tensor:
    """SafeDICE's :math:`\\nu` objective (Jang et al., 2023, the log-sum-exp form of its reference code):
    :math:`\\log E_U[\\exp A_\\nu] + (1-\\gamma) E_{\\rho_0}[\\nu(s_0)]`, the dual of
    :math:`\\max_d E_d[r] - D_{KL}(d \\| d_U) = -D_{KL}(d \\| d_P)` (with :math:`r = \\log d_P/d_U`).

    Examples:
        >>> round(safedice_dual(torch.ones(3), torch.zeros(4), gamma=0.9).item(), 4)
        0.1
    """
    return log_mean_exp(advantage) + (1.0 - gamma) * init_nu.mean()


#: SafeDICE's closed-form correction :math:`\log w^*(s,a) = A_\nu(s,a) - 1` (:math:`w^* = d^*/d_U`): the same
#: function of the advantage as SpoilDICE's Eq. (11), so one function serves both.
safedice_log_weight = closed_form_log_weight


#: What writes the logit :class:`SafeDICELoss` reads, said when its role lacks it.
LOGIT_WRITER = (
    "the non-preferred discriminator's logit, written by PUDiscriminatorLoss.log_ratio_module("
    "'log_ratio_nonpreferred') in SafeDICE's pre-training (buffers.annotate)"
)


class SafeDICELoss(DICELoss):
    r"""SafeDICE's dual objective over :math:`\nu` (Jang et al., 2023), with a frozen non-preferred discriminator.

    SafeDICE (`reference code <https://github.com/jys5609/SafeDICE>`_) imitates the preferred part of the
    unlabeled data, :math:`\min_d D_{KL}(d \| d_P)` over stationary distributions, where :math:`d_P` is known
    only through :math:`d_U = \alpha d_N + (1-\alpha) d_P` and demonstrations :math:`D_N` of non-preferred
    behaviour. The `SpoilDICE paper <https://anonymous.4open.science/r/iclr2026_spoildice-214C>`_ (section 5)
    uses the unsafe demonstrations as :math:`D_N`. A discriminator :math:`D` of :math:`D_N` against
    :math:`D_U` (e.g. :class:`~spoil_torchrl.objectives.PUDiscriminatorLoss` with ``positive="nonpreferred"``,
    pre-trained and frozen) gives the reward :func:`safedice_reward` :math:`r = \log d_P/d_U`; with
    :math:`A_\nu = r + \gamma \nu(s')(1 - d) - \nu(s)` (:math:`d` the *terminated* flag):

    * ``loss_nu`` is :func:`safedice_dual` plus a gradient penalty :math:`c\,E[\lVert \nabla_s \nu(\tilde s)
      \rVert^2]` (Table J: 10) on unlabeled states, on states between initial and unlabeled states and between
      :math:`s` and :math:`s'` (:func:`~spoil_torchrl.objectives.dice.state_terms`; the reference
      interpolates with the non-preferred states instead).

    The loss reads the discriminator's *logit* (:math:`\log d_N/d_U`, what
    :class:`~spoil_torchrl.objectives.LogRatio` writes) and takes :math:`D = \sigma(\text{logit})`. :math:`\alpha`
    is fixed here; the reference's "auto" value is :func:`safedice_auto_alpha` of :math:`D` over all of
    :math:`D_U`, which the recipe computes once after pre-training.

    The reference code also standardises the reward, :math:`(r - \bar r)/s_r` with the mean and standard
    deviation over :math:`D_U` computed once; ``reward_mean`` / ``reward_std`` do the same (defaults 0 and 1:
    the plain reward). The shift changes nothing (:math:`\nu`'s offset absorbs it) but the scale acts as the
    inverse weight of the KL term, so the standardised objective is :math:`\max_d E_d[r]/s_r - D_{KL}(d\|d_U)`.

    The self-normalised weights :math:`\tilde w \propto \exp(A_\nu - 1)` (batch mean 1, computed after
    subtracting the batch max: the reference exponentiates without it and overflows) are written, detached,
    into the *input* tensordict at ``(unlabeled, weight)`` for
    ``WeightedBCLoss(actor, role="unlabeled", weight="dice_weight")``.

    Args:
        nu_network (TensorDictModule): :math:`\nu(s)`, reading its ``in_keys`` inside a role and writing a scalar.

    Keyword Args:
        alpha (float): share of :math:`d_N` in :math:`d_U`, in [0, 1) (Table J: "auto", see above).
        gamma (float): discount in (0, 1). Default 0.99 (Table J).
        gradient_penalty (float): coefficient of the :math:`\nu` gradient penalty; 0 disables.
            Default 1e-6 (on standardised states; see CONTRIBUTING.md).
        reward_mean (float): subtracted from the reward. Default 0.
        reward_std (float): the reward is divided by it (> 0). Default 1.
        reduction (str): only ``"mean"``: the log-sum-exp couples the samples of a batch.

    Output keys: ``loss_nu`` and detached diagnostics ``alpha``, ``reward_mean`` (of the batch, after
    standardisation), ``clipped_fraction`` (share of the batch with :math:`D > 1/(1+\alpha)`, where
    :func:`safedice_reward` clips), ``log_weight_mean``, ``weight_max``, ``effective_sample_size``, ``nu_init``
    and ``advantage_mean``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from spoil_torchrl.modules import make_value_network
        >>> loss = SafeDICELoss(make_value_network(3, hidden_cells=(16,)), alpha=0.3)
        >>> n = 8
        >>> unlabeled = TensorDict({
        ...     "observation": torch.randn(n, 3),
        ...     "next": {"observation": torch.randn(n, 3), "terminated": torch.zeros(n, 1, dtype=torch.bool)},
        ...     "log_ratio_nonpreferred": torch.randn(n, 1),
        ... }, [n])
        >>> init = TensorDict({"observation": torch.randn(4, 3)}, [4])
        >>> batch = TensorDict({"unlabeled": unlabeled, "init": init}, [])
        >>> loss(batch)["loss_nu"].backward()
        >>> round(batch["unlabeled", "dice_weight"].mean().item(), 4)
        1.0
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys.

        Attributes:
            unlabeled (NestedKey): sub-tensordict of unlabeled transitions. Defaults to ``"unlabeled"``.
            init (NestedKey): sub-tensordict of initial states. Defaults to ``"init"``.
            next (NestedKey): inside ``unlabeled``, where the next state's entries live. Defaults to ``"next"``.
            terminated (NestedKey): inside ``unlabeled``. Defaults to ``("next", "terminated")``.
            logit (NestedKey): inside ``unlabeled``, the discriminator's logit :math:`\\log d_N/d_U`. Defaults
                to ``"log_ratio_nonpreferred"``.
            weight (NestedKey): inside ``unlabeled``, where the detached weights are written. Defaults to
                ``"dice_weight"``.
            advantage (NestedKey): inside ``unlabeled``, where the detached advantage (the exponent of the
                weights) is written, for diagnostics. Defaults to ``"dice_advantage"``.
        """

        unlabeled: NestedKey = "unlabeled"
        init: NestedKey = "init"
        next: NestedKey = "next"
        terminated: NestedKey = ("next", "terminated")
        logit: NestedKey = "log_ratio_nonpreferred"
        weight: NestedKey = "dice_weight"
        advantage: NestedKey = "dice_advantage"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = [
        "loss_nu",
        "alpha",
        "reward_mean",
        "clipped_fraction",
        "log_weight_mean",
        "weight_max",
        "effective_sample_size",
        "nu_init",
        "advantage_mean",
    ]

    nu_network: TensorDictModule
    nu_network_params: TensorDictParams
    target_nu_network_params: TensorDictParams

    def __init__(
        self,
        nu_network: TensorDictModule,
        *,
        alpha: float,
        gamma: float = 0.99,
        gradient_penalty: float = 1e-6,
        reward_mean: float = 0.0,
        reward_std: float = 1.0,
        reduction: str | None = None,
    ) -> None:
        super().__init__()
        self._setup_dual(nu_network, gamma=gamma, gradient_penalty=gradient_penalty, reduction=reduction)
        if not 0.0 <= alpha < 1.0:
            raise ValueError(f"alpha must lie in [0, 1), got {alpha}")
        if not (reward_std > 0 and math.isfinite(reward_std) and math.isfinite(reward_mean)):
            raise ValueError(f"reward_std must be a positive number, got {reward_std} (mean {reward_mean})")
        self.alpha = float(alpha)
        self.reward_mean = float(reward_mean)
        self.reward_std = float(reward_std)

    #: what the vectorised step takes per seed from each seed's inputs, so seeds with other values share a step
    per_seed = ("alpha", "reward_mean", "reward_std")

    @property
    def dual_role(self) -> NestedKey:
        return self.tensor_keys.unlabeled

    @property
    def in_keys(self) -> list[NestedKey]:
        return self._role_in_keys(self.tensor_keys.unlabeled, self.tensor_keys.logit)

    def reward(self, logit: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(probability, reward)`` of the unlabeled transitions from the D_N-vs-D_U discriminator's logit:
        :func:`safedice_reward`, standardised with ``reward_mean`` / ``reward_std``."""
        probability = torch.sigmoid(logit)
        return probability, (safedice_reward(probability, self.alpha) - self.reward_mean) / self.reward_std

    def diagnostics(
        self,
        init_nu: torch.Tensor,
        advantage: torch.Tensor,
        log_weights: torch.Tensor,
        weights: torch.Tensor,
        probability: torch.Tensor,
        reward: torch.Tensor,
        alpha: torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor]:
        """The detached diagnostics output beside ``loss_nu`` (see the class docstring), from nu, the advantage,
        its log weights (:func:`safedice_log_weight`) and their self-normalised weights, and the reward.
        ``alpha`` (a 0-d tensor) stands in for the loss's own (a vectorised step of several seeds passes each
        seed's)."""
        with torch.no_grad():
            dtype = advantage.dtype
            alpha = torch.tensor(self.alpha, device=advantage.device) if alpha is None else alpha
            alpha = alpha.to(dtype)
            return {
                "alpha": alpha,
                "reward_mean": reward.mean(),
                "clipped_fraction": (probability > 1.0 / (1.0 + alpha)).to(dtype).mean(),
                **weight_diagnostics(log_weights, weights),
                "nu_init": init_nu.detach().mean(),
                "advantage_mean": advantage.detach().mean(),
            }

    def inputs(self, tensordict: TensorDictBase, produced: frozenset = frozenset()) -> Tensors:
        """The dual's inputs (:meth:`DICELoss.inputs`), and the probability, reward (:meth:`reward`) and
        ``alpha`` of the unlabeled transitions. The reward is a function of the data and of settings the recipe
        derives from each seed's discriminator, so it is an input: seeds with other values share one
        vectorised step (:attr:`per_seed`)."""
        data = get_role(tensordict, self.dual_role)
        logit = role_entry(data, self.dual_role, self.tensor_keys.logit, LOGIT_WRITER)
        logit = logit.reshape(data.batch_size.numel())
        dtype = next(iter(self.nu_network_params.values(True, True))).dtype
        probability, reward = self.reward(logit.detach().to(dtype))
        alpha = torch.tensor(self.alpha, dtype=dtype, device=logit.device)
        return {**super().inputs(tensordict), "probability": probability, "reward": reward, "alpha": alpha}

    def terms(self, params: Tensors, x: Tensors, produced: dict) -> tuple[torch.Tensor, Tensors]:
        """``loss_nu`` (with the gradient penalty) and the diagnostics; the self-normalised weights and the
        advantage go into ``produced``."""
        init_nu, current_nu, next_nu, penalty = self.nu_terms(params, x)
        probability, reward = x["probability"], x["reward"]
        advantage = dice_advantage(reward, current_nu, bellman_backup(next_nu, x["terminated"], self.gamma))
        loss_nu = safedice_dual(init_nu, advantage, self.gamma) + penalty
        with torch.no_grad():
            log_weights = safedice_log_weight(advantage.detach())
            weights = self_normalized_weights(log_weights)
        self._produce(produced, weights, advantage)
        diagnostics = self.diagnostics(
            init_nu, advantage, log_weights, weights, probability, reward, alpha=x["alpha"]
        )
        return loss_nu, {"loss_nu": loss_nu, **diagnostics}
