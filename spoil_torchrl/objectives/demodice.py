"""The DemoDICE dual over nu (Kim et al., 2022): the baselines DemoDICE-S / DemoDICE-U of section 5."""

from __future__ import annotations

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


def demodice_dual(init_nu: torch.Tensor, advantage: torch.Tensor, alpha: float, gamma: float) -> torch.Tensor:
    """DemoDICE's :math:`\\nu` objective (Kim et al., 2022, the log-sum-exp form of its reference code):
    :math:`(1+\\alpha) \\log E_R[\\exp(A_\\nu / (1+\\alpha))] + (1-\\gamma) E_{\\rho_0}[\\nu(s_0)]`.

    It is the dual of :math:`\\max_d E_d[r] - (1+\\alpha) D_{KL}(d \\| d_R)` over stationary distributions, with
    :math:`d_R` the distribution of the samples (the regularisation role). (The reference uses ``logsumexp``
    instead of the mean: a constant :math:`(1+\\alpha)\\log n` apart.)

    Examples:
        >>> demodice_dual(torch.zeros(3), torch.zeros(4), alpha=0.1, gamma=0.9).item()
        0.0
        >>> round(demodice_dual(torch.ones(3), torch.full((4,), 1.1), alpha=0.1, gamma=0.9).item(), 4)
        1.2
    """
    temperature = 1.0 + alpha
    return temperature * log_mean_exp(advantage / temperature) + (1.0 - gamma) * init_nu.mean()


def demodice_log_weight(advantage: torch.Tensor, alpha: float) -> torch.Tensor:
    """DemoDICE's closed-form correction :math:`\\log w^*(s,a) = A_\\nu(s,a) / (1+\\alpha) - 1` (:math:`w^* =
    d^*/d_R`), kept in log space.

    Examples:
        >>> demodice_log_weight(torch.tensor([1.1]), alpha=0.1).exp().item()
        1.0
    """
    return advantage / (1.0 + alpha) - 1.0


def demodice_diagnostics(
    init_nu: torch.Tensor,
    advantage: torch.Tensor,
    log_weights: torch.Tensor,
    weights: torch.Tensor,
    reward: torch.Tensor,
) -> dict[str, torch.Tensor]:
    """The detached diagnostics :class:`DemoDICELoss` outputs beside ``loss_nu`` (see its docstring), from nu,
    the advantage, its log weights (:func:`demodice_log_weight`) and their self-normalised weights.

    Examples:
        >>> z, one = torch.zeros(2), torch.ones(2)
        >>> out = demodice_diagnostics(z, z, z - 1, one, one)
        >>> out["effective_sample_size"].item(), out["reward_mean"].item()
        (1.0, 1.0)
    """
    with torch.no_grad():
        return {
            **weight_diagnostics(log_weights, weights),
            "reward_mean": reward.mean(),
            "nu_init": init_nu.detach().mean(),
            "advantage_mean": advantage.detach().mean(),
        }


#: What writes the reward :class:`DemoDICELoss` reads, said when its role lacks it.
REWARD_WRITER = (
    "the reward, written by DemoDICE's pre-training (buffers.annotate): C_P's log-ratio "
    "(PUDiscriminatorLoss.log_ratio_module()) for DemoDICE-S, log r_P + alpha log r_S for DemoDICE-U"
)


class DemoDICELoss(DICELoss):
    r"""DemoDICE's dual objective over :math:`\nu` (Kim et al., 2022), regularised toward one role's data.

    DemoDICE (`reference code <https://github.com/geon-hyeong/imitation-dice>`_) solves

    .. math:: \min_d D_{KL}(d \| d_P) + \alpha D_{KL}(d \| d_R)
              = \max_d E_d[\log (d_P/d_R)] - (1+\alpha) D_{KL}(d \| d_R)

    over stationary distributions, with samples of :math:`d_R` (the ``regularization`` role). With the reward
    :math:`r = \log(d_P/d_R)` (read from the ``reward`` key of the role) and
    :math:`A_\nu = r + \gamma \nu(s')(1 - d) - \nu(s)` (:math:`d` the *terminated* flag), the dual is
    :func:`demodice_dual` and the correction :math:`w^* = d^*/d_R \propto \exp(A_\nu/(1+\alpha))`.
    The `SpoilDICE paper <https://anonymous.4open.science/r/iclr2026_spoildice-214C>`_ uses two variants
    (section 5, Table J: :math:`\alpha = 0.1`, :math:`\nu` gradient penalty 10):

    * **DemoDICE-U** (``regularization="unlabeled"``): the paper's DemoDICE-U regularises toward :math:`d_S`
      like DemoDICE-S and differs only in sampling :math:`d_U`. With :math:`w = d/d_U`,
      :math:`D_{KL}(d\|d_P) + \alpha D_{KL}(d\|d_S) = (1+\alpha) D_{KL}(d\|d_U) - E_d[\log r_P + \alpha \log r_S]`,
      so it is this dual on :math:`D_U` with the reward :math:`r = \log \hat r_P + \alpha \log \hat r_S`
      (logits of :math:`C_P` and :math:`C_S`, Eq. 18; the recipe writes it at ``"demodice_reward"``). With
      :math:`r = \log \hat r_P` alone (the default ``reward``) it is the original DemoDICE with :math:`D_U` as
      its union data. The reference's reward is :math:`-\log(1/(\sigma(c)+10^{-3}) - 1 + 10^{-3})`, the same
      logit up to a clip of about :math:`[-6.9, 13.8]`; we use the logit itself.
    * **DemoDICE-S** (``regularization="safe"``): the same objective with :math:`d_R = d_S`, so
      :math:`r = \log d_P/d_S` on the safe transitions. The recipe obtains it, as the reference obtains its
      reward, from one discriminator: :math:`C_{PS}` trained on Eq. (16) with :math:`D_S` in place of
      :math:`D_U` (positive role ``performant``, negative role ``safe``), whose logit is :math:`\log d_P/d_S`;
      it is written at ``"log_ratio_performant_safe"`` in the safe role. (Equivalently, since
      :math:`d_P/d_S = (d_P/d_U)/(d_S/d_U)`, one may annotate :math:`\log \hat r_P - \log \hat r_S` and point
      ``reward`` at it; that needs two discriminators and adds both their errors.)

    With the reward and the samples matching, the optimum is exactly
    :func:`~spoil_torchrl.tabular.solve_demodice` with :math:`d_R` as its second distribution:
    ``solve_demodice(mdp, d_P, d_S, alpha)`` for DemoDICE-S, ``solve_demodice(mdp, d_P, d_U, alpha)`` for
    DemoDICE-U (``tests/tabular/test_demodice_convergence.py``). The weights only live on the role's samples,
    so DemoDICE-S's :math:`d^*` lives on :math:`supp(d_S)`, as the exact solution does.

    * ``loss_nu`` is :func:`demodice_dual` plus a gradient penalty :math:`c\,E[\lVert \nabla_s \nu(\tilde s)
      \rVert^2]` on the role's states, on states between initial and role states and between :math:`s` and
      :math:`s'` (:func:`~spoil_torchrl.objectives.dice.state_terms`; the reference interpolates
      with its expert states, which this one-role dual does not have, as in SpoilDICE).

    The self-normalised weights :math:`\tilde w = w^*/\overline{w^*}` (batch mean 1, computed after subtracting
    the batch max, so they never overflow) are written, detached, into the *input* tensordict at
    ``(regularization, weight)``, where ``WeightedBCLoss(actor, role=regularization, weight="dice_weight")``
    reads them (Eq. 20 on the role's data).

    Args:
        nu_network (TensorDictModule): :math:`\nu(s)`, reading its ``in_keys`` inside a role and writing a scalar.

    Keyword Args:
        alpha (float): weight :math:`\alpha \ge 0` of the :math:`D_{KL}(d \| d_R)` regulariser. Default 0.1
            (Table J).
        gamma (float): discount in (0, 1). Default 0.99 (Table J).
        gradient_penalty (float): coefficient of the :math:`\nu` gradient penalty; 0 disables.
            Default 1e-4 (on standardised states; see CONTRIBUTING.md).
        regularization (NestedKey, optional): the role :math:`d_R` (its transitions are the samples, its
            ``reward`` entry is :math:`\log d_P/d_R`). Default ``"unlabeled"`` (DemoDICE-U).
        reward (NestedKey, optional): inside the role, :math:`\log d_P/d_R`. Default ``"log_ratio_performant"``.
        reduction (str): only ``"mean"``: the log-sum-exp couples the samples of a batch, so the objective has no
            per-sample form.

    Output keys: ``loss_nu`` and detached diagnostics ``log_weight_mean`` (:math:`\log E_R[w^*]`; the dual
    leaves :math:`\nu`'s constant offset free, so only its changes are informative), ``weight_max`` (largest
    :math:`\tilde w`), ``effective_sample_size`` (Kish ESS of :math:`\tilde w` as a fraction of the batch),
    ``reward_mean``, ``nu_init`` and ``advantage_mean``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from spoil_torchrl.modules import make_value_network
        >>> loss = DemoDICELoss(make_value_network(3, hidden_cells=(16,)), alpha=0.1, regularization="safe",
        ...                     reward="log_ratio_performant_safe")
        >>> n = 8
        >>> safe = TensorDict({
        ...     "observation": torch.randn(n, 3),
        ...     "next": {"observation": torch.randn(n, 3), "terminated": torch.zeros(n, 1, dtype=torch.bool)},
        ...     "log_ratio_performant_safe": torch.randn(n, 1),
        ... }, [n])
        >>> batch = TensorDict({"safe": safe, "init": TensorDict({"observation": torch.randn(4, 3)}, [4])}, [])
        >>> loss(batch)["loss_nu"].backward()
        >>> batch["safe", "dice_weight"].shape, round(batch["safe", "dice_weight"].mean().item(), 4)
        (torch.Size([8, 1]), 1.0)
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys.

        Attributes:
            regularization (NestedKey): sub-tensordict of the transitions of :math:`d_R`. Defaults to
                ``"unlabeled"``.
            init (NestedKey): sub-tensordict of initial states. Defaults to ``"init"``.
            next (NestedKey): inside ``regularization``, where the next state's entries live. Defaults to
                ``"next"``.
            terminated (NestedKey): inside ``regularization``. Defaults to ``("next", "terminated")``.
            reward (NestedKey): inside ``regularization``, :math:`\\log d_P/d_R`. Defaults to
                ``"log_ratio_performant"``.
            weight (NestedKey): inside ``regularization``, where the detached weights are written. Defaults to
                ``"dice_weight"``.
            advantage (NestedKey): inside ``regularization``, where the detached advantage (the exponent of the
                weights) is written, for diagnostics. Defaults to ``"dice_advantage"``.
        """

        regularization: NestedKey = "unlabeled"
        init: NestedKey = "init"
        next: NestedKey = "next"
        terminated: NestedKey = ("next", "terminated")
        reward: NestedKey = "log_ratio_performant"
        weight: NestedKey = "dice_weight"
        advantage: NestedKey = "dice_advantage"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = [
        "loss_nu",
        "log_weight_mean",
        "weight_max",
        "effective_sample_size",
        "reward_mean",
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
        alpha: float = 0.1,
        gamma: float = 0.99,
        gradient_penalty: float = 1e-4,
        regularization: NestedKey | None = None,
        reward: NestedKey | None = None,
        reduction: str | None = None,
    ) -> None:
        super().__init__()
        self._setup_dual(nu_network, gamma=gamma, gradient_penalty=gradient_penalty, reduction=reduction)
        if not alpha >= 0.0:  # also rejects NaN
            raise ValueError(f"alpha must be >= 0, got {alpha}")
        self.alpha = float(alpha)
        keys = {"regularization": regularization, "reward": reward}
        self.set_keys(**{name: key for name, key in keys.items() if key is not None})

    @property
    def dual_role(self) -> NestedKey:
        return self.tensor_keys.regularization

    @property
    def in_keys(self) -> list[NestedKey]:
        return self._role_in_keys(self.tensor_keys.regularization, self.tensor_keys.reward)

    def inputs(self, tensordict: TensorDictBase, produced: frozenset = frozenset()) -> Tensors:
        """The dual's inputs (:meth:`DICELoss.inputs`) and the reward :math:`\\log d_P/d_R` of the role."""
        data = get_role(tensordict, self.dual_role)
        reward = role_entry(data, self.dual_role, self.tensor_keys.reward, REWARD_WRITER)
        reward = reward.reshape(data.batch_size.numel())
        return {**super().inputs(tensordict), "reward": reward}

    def terms(self, params: Tensors, x: Tensors, produced: dict) -> tuple[torch.Tensor, Tensors]:
        """``loss_nu`` (with the gradient penalty) and the diagnostics; the self-normalised weights and the
        advantage go into ``produced``."""
        init_nu, current_nu, next_nu, penalty = self.nu_terms(params, x)
        reward = x["reward"].detach().to(current_nu.dtype)  # data of a frozen discriminator
        advantage = dice_advantage(reward, current_nu, bellman_backup(next_nu, x["terminated"], self.gamma))
        loss_nu = demodice_dual(init_nu, advantage, self.alpha, self.gamma) + penalty
        with torch.no_grad():
            log_weights = demodice_log_weight(advantage.detach(), self.alpha)
            weights = self_normalized_weights(log_weights)
        self._produce(produced, weights, advantage)
        diagnostics = demodice_diagnostics(init_nu, advantage, log_weights, weights, reward)
        return loss_nu, {"loss_nu": loss_nu, **diagnostics}
