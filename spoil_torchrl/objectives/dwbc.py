"""DWBC (Xu et al., 2022): discriminator-weighted behavioural cloning, the baseline DWBC-S of section 5."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase, TensorDictParams
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule
from tensordict.utils import NestedKey
from torch import nn

from spoil_torchrl.objectives.functional import check_reduction
from spoil_torchrl.objectives.keys import get_role, role_key
from spoil_torchrl.objectives.pure import PureLoss, PureNetwork, PurePolicy, Tensors, flat_rows
from spoil_torchrl.objectives.weighted_bc import weighted_nll

#: The reference code's range of :math:`\log \pi(a|s)` per action dimension, mapped onto [0, 1].
LOG_PROB_MIN, LOG_PROB_MAX = -20.0, 10.0
#: The reference code clips the discriminator's probability :math:`D` to this range.
D_MIN, D_MAX = 0.1, 0.9
#: Unlabeled samples with :math:`D` below this get weight 0 (the reference code).
D_CUT = 0.5


def log_prob_feature(log_prob: torch.Tensor, action_dim: int) -> torch.Tensor:
    """The discriminator's policy input (DWBC's reference code): :math:`\\log \\pi(a|s)` per action dimension,
    clipped to [-20, 10] and mapped onto [0, 1]; detached, so the discriminator loss never trains the policy.

    Examples:
        >>> log_prob_feature(torch.tensor([-50.0, -10.0, 100.0]), action_dim=2).tolist()  # -25, -5, 50 per dim
        [0.0, 0.5, 1.0]
    """
    per_dim = log_prob.detach() / action_dim
    return (per_dim.clamp(LOG_PROB_MIN, LOG_PROB_MAX) - LOG_PROB_MIN) / (LOG_PROB_MAX - LOG_PROB_MIN)


def dwbc_probability(logit: torch.Tensor) -> torch.Tensor:
    """DWBC's discriminator output :math:`D = \\text{clip}(\\sigma(\\text{logit}), 0.1, 0.9)` (the reference code).

    Examples:
        >>> [round(x, 4) for x in dwbc_probability(torch.tensor([-10.0, 0.0, 10.0])).tolist()]
        [0.1, 0.5, 0.9]
    """
    return torch.sigmoid(logit).clamp(D_MIN, D_MAX)


def dwbc_discriminator_loss(d_expert: torch.Tensor, d_unlabeled: torch.Tensor, eta: float) -> torch.Tensor:
    """DWBC's positive-unlabeled discriminator risk (Xu et al., 2022) with class prior :math:`\\eta`:
    :math:`E_E[-\\log D] - E_E[-\\log(1-D)] + E_U[-\\log(1-D)]/\\eta`.

    This is DWBC's unbiased PU risk :math:`\\eta E_E[-\\log D] + E_U[-\\log(1-D)] - \\eta E_E[-\\log(1-D)]` divided
    by :math:`\\eta`, as the reference code writes it. The risk alone is unbounded below where
    :math:`\\eta d_E > d_U`; the clip of :math:`D` to [0.1, 0.9] (:func:`dwbc_probability`) bounds it (the
    non-negative risk :func:`~spoil_torchrl.objectives.nnpu_risks` is the other cure; DWBC uses the clip).

    Examples:
        >>> half = torch.full((4,), 0.5)  # -log 0.5 - (-log 0.5) + (-log 0.5) / 0.5 = 2 log 2
        >>> round(dwbc_discriminator_loss(half, half, eta=0.5).item(), 4)
        1.3863
    """
    return (
        -torch.log(d_expert).mean() + torch.log1p(-d_expert).mean() - torch.log1p(-d_unlabeled).mean() / eta
    )


def dwbc_expert_weight(d: torch.Tensor, alpha: float, eta: float, offset: float = 1.0) -> torch.Tensor:
    """Weight of :math:`-\\log \\pi` on an expert sample: :math:`\\alpha - \\eta / (D(1-D)) - 1` (the reference
    code's ``alpha * bc_loss - corr_loss_e``; DWBC's paper writes it without the ``- 1``, i.e. ``offset=0``).

    Examples:
        >>> round(dwbc_expert_weight(torch.tensor(0.5), alpha=7.5, eta=0.5).item(), 4)  # 7.5 - 2 - 1
        4.5
    """
    return alpha - eta / (d * (1.0 - d)) - offset


def dwbc_unlabeled_weight(d: torch.Tensor, offset: float = 1.0) -> torch.Tensor:
    """Weight of :math:`-\\log \\pi` on an unlabeled sample: :math:`1/(1-\\tilde D) - 1`, :math:`\\tilde D = D` where
    :math:`D \\ge 0.5` and 0 elsewhere (the reference code's ``corr_loss_o``), i.e. :math:`D/(1-D)` on the kept
    samples and exactly 0 on the others. DWBC's paper writes :math:`1/(1-D)` (``offset=0``; the cut samples then
    keep weight 1).

    Examples:
        >>> [round(x, 4) for x in dwbc_unlabeled_weight(torch.tensor([0.2, 0.5, 0.8])).tolist()]  # 0, 1, 0.8/0.2
        [0.0, 1.0, 4.0]
    """
    kept = torch.where(d >= D_CUT, d, torch.zeros_like(d))
    return 1.0 / (1.0 - kept) - offset


def dwbc_outputs(
    log_prob: torch.Tensor, logit: torch.Tensor, n_expert: int, alpha: float, eta: float, offset: float
) -> dict[str, torch.Tensor]:
    """:class:`DWBCLoss`'s outputs from the policy's log-likelihoods and the discriminator's logits of the expert
    rows (the first ``n_expert``) and the unlabeled rows: ``loss_discriminator``, ``loss_actor`` and the detached
    diagnostics. :meth:`DWBCLoss.terms` calls it.

    Examples:
        >>> out = dwbc_outputs(torch.zeros(4), torch.zeros(4), 2, alpha=7.5, eta=0.5, offset=0.1)
        >>> round(out["d_expert"].item(), 4), sorted(k for k in out if k.startswith("loss_"))
        (0.5, ['loss_actor', 'loss_discriminator'])
    """
    d = dwbc_probability(logit)
    d_expert, d_unlabeled = d[:n_expert], d[n_expert:]
    loss_discriminator = dwbc_discriminator_loss(d_expert, d_unlabeled, eta)
    with torch.no_grad():
        w_expert = dwbc_expert_weight(d_expert, alpha, eta, offset)
        w_unlabeled = dwbc_unlabeled_weight(d_unlabeled, offset)
    lp_expert, lp_unlabeled = log_prob[:n_expert], log_prob[n_expert:]
    loss_actor = weighted_nll(lp_expert, w_expert).mean() + weighted_nll(lp_unlabeled, w_unlabeled).mean()
    return {
        "loss_discriminator": loss_discriminator,
        "loss_actor": loss_actor,
        "d_expert": d_expert.detach().mean(),
        "d_unlabeled": d_unlabeled.detach().mean(),
        "unlabeled_kept": (d_unlabeled.detach() >= D_CUT).float().mean(),
        "expert_weight_mean": w_expert.mean(),
        "unlabeled_weight_mean": w_unlabeled.mean(),
        "log_prob_expert": lp_expert.detach().mean(),
        "log_prob_unlabeled": lp_unlabeled.detach().mean(),
    }


class DWBCLoss(PureLoss):
    r"""DWBC (Xu et al., 2022): a discriminator and a discriminator-weighted BC policy, trained jointly.

    DWBC (`reference code <https://github.com/ryanxhr/DWBC>`_) imitates an expert role :math:`D_E` with the help
    of an unlabeled (DWBC: "offline") role :math:`D_U` of mixed quality. A discriminator :math:`D(s, a,
    \log\pi(a|s))` of :math:`D_E` against :math:`D_U`, whose input includes the policy's (detached, normalised:
    :func:`log_prob_feature`) log-likelihood and whose output is clipped to [0.1, 0.9]
    (:func:`dwbc_probability`), is trained on the PU risk :func:`dwbc_discriminator_loss` with class prior
    :math:`\eta`; the policy on

    .. math:: E_E\Big[\big(\alpha - \tfrac{\eta}{D(1-D)} - 1\big)(-\log\pi)\Big]
              + E_U\Big[\big(\tfrac{1}{1-\tilde D} - 1\big)(-\log\pi)\Big],
              \quad \tilde D = D\,\mathbb 1[D \ge 0.5]

    (:func:`dwbc_expert_weight`, :func:`dwbc_unlabeled_weight`; :math:`D` detached), so unlabeled samples the
    discriminator finds expert-like get weight :math:`D/(1-D) \in [1, 9]` and the others none.

    **The "+1 / -1" of the reference's corr losses** (questioned in its issue #2, unanswered) are kept by default
    (``reference_offsets=True``): they are what the published numbers and the hyper-parameters
    :math:`\alpha = 7.5, \eta = 0.5` (Table J) were obtained with, the ``-1`` is what makes the :math:`D < 0.5`
    cut remove samples at all (without it they keep weight 1, i.e. plain BC on them), and with
    :math:`\alpha = 7.5` every expert weight stays positive (at least :math:`7.5 - 1 - 0.5/0.09 = 0.94`).
    ``reference_offsets=False`` gives the paper's weights :math:`\alpha - \eta/(D(1-D))` and :math:`1/(1-\tilde D)`.
    Hyper-parameters for which some expert weight could be negative (the actor loss would be unbounded below)
    raise.

    **DWBC-S** (the `SpoilDICE paper <https://anonymous.4open.science/r/iclr2026_spoildice-214C>`_, section 5:
    "recover performant behaviors from safe demonstrations") uses ``expert="performant"`` and
    ``unlabeled="safe"``: the expert-like (performant) behaviour is recovered from the safe demonstrations. Table J
    agrees (DWBC-S lists a :math:`C_P` learning rate and no :math:`C_S`), and so does Table 1, where DWBC-S's costs
    track BC's on :math:`D_P`. The defaults (``unlabeled="unlabeled"``) are the original DWBC with :math:`D_U`.

    The policy feature is the joint :math:`\log\pi(a|s)` divided by the action dimension (one number, for any
    distribution) and concatenated with :math:`(s, a)` (``make_discriminator(..., extra_inputs=...)``); the
    reference feeds its tanh-Normal's per-dimension log-densities, a vector, through a layer of their own. Both
    use the reference's clip to [-20, 10] per dimension.

    The two terms reach disjoint parameters: ``loss_discriminator`` only the discriminator's (the policy enters
    it only through the detached feature), ``loss_actor`` only the policy's (:math:`D` is detached). The reference
    updates the discriminator once every 100 policy steps; that is the recipe's optimiser schedule, not the loss.

    Args:
        actor_network (ProbabilisticTensorDictSequential): the policy; ``get_dist`` gives :math:`\pi(\cdot|s)`.
        discriminator_network (TensorDictModule): maps its ``in_keys`` to a logit; one in_key (``log_prob_input``)
            receives the policy feature, the others are read inside each role (e.g.
            ``make_discriminator(obs_dim, act_dim, extra_inputs={"policy_log_prob": 1})``).

    Keyword Args:
        alpha (float): weight :math:`\alpha` of the expert NLL. Default 7.5 (Table J, reference).
        eta (float): PU class prior :math:`\eta \in (0, 1)`. Default 0.5 (Table J, reference).
        reference_offsets (bool): keep the reference code's ``+1`` / ``-1`` (default) or use the paper's weights.
        expert (NestedKey, optional): the expert role. Default ``"performant"``.
        unlabeled (NestedKey, optional): the unlabeled (offline) role. Default ``"unlabeled"``; DWBC-S: ``"safe"``.
        reduction (str): only ``"mean"``: both terms combine two roles of their own batch sizes (and the PU risk
            is a batch-level risk), so there is no per-sample form.

    Output keys: ``loss_discriminator``, ``loss_actor`` and the detached diagnostics ``d_expert`` /
    ``d_unlabeled`` (mean :math:`D`), ``unlabeled_kept`` (share of :math:`D \ge 0.5`), ``expert_weight_mean``,
    ``unlabeled_weight_mean``, ``log_prob_expert`` and ``log_prob_unlabeled``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from spoil_torchrl.modules import make_actor, make_discriminator
        >>> actor = make_actor(3, 2, hidden_cells=(16,), distribution="normal")
        >>> disc = make_discriminator(3, 2, hidden_cells=(16,), extra_inputs={"policy_log_prob": 1})
        >>> loss = DWBCLoss(actor, disc, expert="performant", unlabeled="safe")  # DWBC-S
        >>> def role(n):
        ...     return TensorDict({"observation": torch.randn(n, 3), "action": torch.rand(n, 2) * 2 - 1}, [n])
        >>> out = loss(TensorDict({"performant": role(8), "safe": role(16)}, []))
        >>> (out["loss_discriminator"] + out["loss_actor"]).backward()
        >>> 0.1 <= out["d_unlabeled"].item() <= 0.9
        True
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys.

        Attributes:
            expert (NestedKey): sub-tensordict of the expert transitions. Defaults to ``"performant"``.
            unlabeled (NestedKey): sub-tensordict of the unlabeled (offline) transitions. Defaults to
                ``"unlabeled"``.
            action (NestedKey): inside each role, the demonstrated action. Defaults to ``"action"``.
            log_prob_input (NestedKey): the discriminator in_key that receives :func:`log_prob_feature` (set by
                the loss, never read from the batch). Defaults to ``"policy_log_prob"``.
        """

        expert: NestedKey = "performant"
        unlabeled: NestedKey = "unlabeled"
        action: NestedKey = "action"
        log_prob_input: NestedKey = "policy_log_prob"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = [
        "loss_discriminator",
        "loss_actor",
        "d_expert",
        "d_unlabeled",
        "unlabeled_kept",
        "expert_weight_mean",
        "unlabeled_weight_mean",
        "log_prob_expert",
        "log_prob_unlabeled",
    ]

    actor_network: ProbabilisticTensorDictSequential
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    discriminator_network: TensorDictModule
    discriminator_network_params: TensorDictParams
    target_discriminator_network_params: TensorDictParams

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        discriminator_network: TensorDictModule,
        *,
        alpha: float = 7.5,
        eta: float = 0.5,
        reference_offsets: bool = True,
        expert: NestedKey | None = None,
        unlabeled: NestedKey | None = None,
        reduction: str | None = None,
    ) -> None:
        super().__init__()
        if not hasattr(actor_network, "get_dist"):
            raise TypeError("actor_network must be a probabilistic actor with a get_dist method")
        if not 0.0 < eta < 1.0:
            raise ValueError(f"eta must lie in (0, 1), got {eta}")
        offset = 1.0 if reference_offsets else 0.0
        lowest = alpha - offset - eta / (D_MIN * (1.0 - D_MIN))  # the expert weight at D = 0.1 or 0.9
        if not lowest >= 0.0:  # also rejects NaN
            raise ValueError(
                f"alpha={alpha} is too small for eta={eta}: the expert weight alpha - eta / (D (1 - D))"
                f"{' - 1' if reference_offsets else ''} would be negative ({lowest:.3f}) at D = {D_MIN}, and the "
                f"actor loss unbounded below; use alpha >= {alpha - lowest:.3f}"
            )
        self.reduction = check_reduction(reduction, allowed=("mean",))
        self.convert_to_functional(actor_network, "actor_network")
        self.convert_to_functional(discriminator_network, "discriminator_network")
        self.alpha = float(alpha)
        self.eta = float(eta)
        self.offset = offset
        keys = {"expert": expert, "unlabeled": unlabeled}
        self.set_keys(**{name: key for name, key in keys.items() if key is not None})

    def _discriminator_inputs(self) -> list[NestedKey]:
        keys = list(self.discriminator_network.in_keys)
        if self.tensor_keys.log_prob_input not in keys:
            raise KeyError(
                f"the discriminator's in_keys {keys} lack the policy input {self.tensor_keys.log_prob_input!r}: "
                "build it with make_discriminator(..., extra_inputs={'policy_log_prob': 1}) or set_keys"
                "(log_prob_input=...)"
            )
        return [k for k in keys if k != self.tensor_keys.log_prob_input]

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        inner = [*self.actor_network.in_keys, keys.action]
        inner += [k for k in self._discriminator_inputs() if k not in inner]
        return [role_key(role, k) for role in (keys.expert, keys.unlabeled) for k in inner]

    functional_params = ("actor_network_params", "discriminator_network_params")

    @property
    def policy(self) -> PurePolicy:
        """The actor as a function of its parameters (:class:`~spoil_torchrl.objectives.pure.PurePolicy`)."""
        return self._pure(
            "actor", lambda: PurePolicy(self.actor_network, self.actor_network_params, "DWBCLoss's actor")
        )

    @property
    def discriminator(self) -> PureNetwork:
        """D(s, a, log pi) as a function of its parameters."""
        return self._pure(
            "discriminator",
            lambda: PureNetwork(
                self.discriminator_network, self.discriminator_network_params, "DWBCLoss's discriminator"
            ),
        )

    def term_parameters(self) -> dict[str, nn.Parameter]:
        policy = self.policy.parameters(self.actor_network_params)
        net = self.discriminator.parameters(self.discriminator_network_params)
        return {
            **{f"policy.{k}": v for k, v in policy.items()},
            **{f"net.{k}": v for k, v in net.items()},
        }

    def check_compilable(self) -> None:
        self.policy.check_compilable()
        self.discriminator.check_compilable()

    def inputs(self, tensordict: TensorDictBase, produced: frozenset = frozenset()) -> Tensors:
        """Each role's states, actions and the discriminator's inputs read from the data."""
        keys, out = self.tensor_keys, {}
        data_keys = self._discriminator_inputs()
        for name, role_name in (("expert", keys.expert), ("unlabeled", keys.unlabeled)):
            role = get_role(tensordict, role_name)
            out[f"{name}.state"] = self.policy.states(role)
            out[f"{name}.action"] = flat_rows(role, keys.action)
            out |= {f"{name}.{i}": flat_rows(role, k) for i, k in enumerate(data_keys)}
        return out

    def terms(self, params: Tensors, x: Tensors, produced: dict) -> tuple[torch.Tensor, Tensors]:
        """``loss_discriminator`` and ``loss_actor`` (:func:`dwbc_outputs`) on both roles, the policy's
        log-likelihood feeding the discriminator."""
        policy_params = {k.removeprefix("policy."): v for k, v in params.items() if k.startswith("policy.")}
        net_params = {k.removeprefix("net."): v for k, v in params.items() if k.startswith("net.")}
        data_keys = self._discriminator_inputs()
        n_expert = x["expert.action"].shape[0]
        action = torch.cat([x["expert.action"], x["unlabeled.action"]])
        states = torch.cat([x["expert.state"], x["unlabeled.state"]])
        log_prob = self.policy.log_prob(policy_params, states, action)
        data = {k: torch.cat([x[f"expert.{i}"], x[f"unlabeled.{i}"]]) for i, k in enumerate(data_keys)}
        data[self.tensor_keys.log_prob_input] = log_prob_feature(log_prob, action[0].numel()).unsqueeze(-1)
        net = self.discriminator
        logit = net(net_params, *(data[k] for k in net.in_keys)).reshape(-1)
        outputs = dwbc_outputs(log_prob, logit, n_expert, self.alpha, self.eta, self.offset)
        return outputs["loss_discriminator"] + outputs["loss_actor"], outputs
