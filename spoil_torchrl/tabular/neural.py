"""The neural SpoilDICE pipeline (Algorithm 1), and the neural DemoDICE baseline, run on a tabular problem with
one-hot features.

Everything here uses the library's real pieces -- TorchRL replay buffers, :class:`PUDiscriminatorLoss`,
:class:`SupportEstimator`, :class:`SpoilDICELoss`, :class:`DemoDICELoss`, :class:`WeightedBCLoss`, and the
offline Trainer of :func:`~spoil_torchrl.trainers.offline_trainer` for every stage -- so that the learned policy's
occupancy can be compared with the exact solutions of
:func:`~spoil_torchrl.tabular.solve_spoildice` and :func:`~spoil_torchrl.tabular.solve_demodice`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.objectives import LossModule

from spoil_torchrl.modules import make_actor, make_discriminator, make_value_network
from spoil_torchrl.objectives import (
    DemoDICELoss,
    LogRatio,
    PUDiscriminatorLoss,
    SpoilDICELoss,
    SupportEstimator,
    WeightedBCLoss,
    annotate,
)
from spoil_torchrl.objectives.support import check_supports_intersect
from spoil_torchrl.tabular.cmdp import occupancy
from spoil_torchrl.tabular.problems import DualDemoProblem
from spoil_torchrl.tabular.sampling import one_hot, sample_initial_states, sample_transitions
from spoil_torchrl.trainers.offline import MultiLossStepper, offline_trainer

ROLES = ("safe", "performant", "unlabeled")


@dataclass
class TabularTrainingConfig:
    """Settings of :func:`train_tabular_spoildice`. One-hot inputs call for larger learning rates than Table J.

    The gradient penalties default to 0 here: a Lipschitz penalty on one-hot inputs would bias the tabular
    ratios and values, which is exactly what this check must not have.
    """

    n_samples: int = 50_000
    n_init: int = 5_000
    batch_size: int = 512
    discriminator_steps: int = 2_000
    dice_steps: int = 4_000
    discriminator_lr: float = 3e-3
    nu_lr: float = 1e-2
    lagrange_lr: float = 1e-2
    actor_lr: float = 1e-2
    discriminator_cells: tuple[int, ...] = (64, 64)
    discriminator_gradient_penalty: float = 0.0
    nu_gradient_penalty: float = 0.0
    kappa: float = 0.001
    init_lagrange: float = 0.0
    seed: int = 0


@dataclass
class TabularTrainingResult:
    """What :func:`train_tabular_spoildice` learned, as tables over states and actions."""

    occupancy: np.ndarray  # [S, A] occupancy of the learned policy
    policy: np.ndarray  # [S, A]
    support: np.ndarray  # [S, A] estimated safe support (bool)
    log_ratio_performant: np.ndarray  # [S, A] learned log r_P
    history: list[dict] = field(default_factory=list)


def _buffer(data: TensorDict, batch_size: int) -> TensorDictReplayBuffer:
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(data.shape[0]), batch_size=batch_size)
    buffer.extend(data)
    return buffer


def _sample(buffers: dict[str, TensorDictReplayBuffer]) -> Callable[[], TensorDict]:
    """A batch source: one fresh batch of every buffer (role -> buffer) per call."""
    return lambda: TensorDict({role: buffer.sample() for role, buffer in buffers.items()}, batch_size=[])


#: A stage's outputs are recorded (``history``, the ``log`` callback) at every this many steps.
RECORD_EVERY = 100


class _RecordingStepper(MultiLossStepper):
    """A :class:`~spoil_torchrl.trainers.MultiLossStepper` that hands the scalar outputs of every
    :data:`RECORD_EVERY`-th step to ``record(step, {loss name: {entry: value}})``."""

    def __init__(self, losses, optimizers, schedulers, record: Callable[[int, dict], None]) -> None:
        super().__init__(losses, optimizers, schedulers)
        self.record, self.steps = record, 0

    def step(self, trainer, sub_batch):
        out = super().step(trainer, sub_batch)
        if self.steps % RECORD_EVERY == 0:
            grouped = {name: {} for name in self.losses}
            for key, value in out.items():
                name, entry = key.split(".", 1)
                grouped[name][entry] = float(value)
            self.record(self.steps, grouped)
        self.steps += 1
        return out


def _train_stage(
    losses: dict[str, LossModule],
    optimizers: list[torch.optim.Optimizer],
    sample: Callable[[], TensorDict],
    steps: int,
    *,
    label: str,
    progress: bool,
    record: Callable[[int, dict], None],
) -> None:
    """``steps`` optimisation steps of ``losses`` (run in order on each batch, one backward pass through the sum
    of their ``loss_*`` terms) through the library's offline Trainer, each optimiser under a cosine schedule
    over the stage, each step on a fresh ``sample()``."""
    schedules = [torch.optim.lr_scheduler.CosineAnnealingLR(o, max(steps, 1)) for o in optimizers]
    if steps > 0:
        stepper = _RecordingStepper(losses, optimizers, schedules, record)
        offline_trainer(
            stepper,
            sample,
            total_steps=steps,
            steps_per_batch=min(RECORD_EVERY, steps),
            progress_bar=progress,
            progress_label=label,
        ).train()


def _safe_roles(problem: DualDemoProblem) -> list[str]:
    """The safe roles: ``["safe"]`` for one constraint, ``safe_0 .. safe_<K-1>`` for ``d_S`` of shape
    ``[K, S, A]``."""
    d_S = np.asarray(problem.d_S)
    return ["safe"] if d_S.ndim == 2 else [f"safe_{k}" for k in range(d_S.shape[0])]


def _support_key(role: str, safe_roles: list[str]) -> str:
    """Where a safe role's support indicator is written: ``safe_support`` for the single constraint."""
    return "safe_support" if safe_roles == ["safe"] else f"{role}_support"


def _all_pairs(n_states: int, n_actions: int) -> TensorDict:
    s, a = np.divmod(np.arange(n_states * n_actions), n_actions)
    return TensorDict({"observation": one_hot(s, n_states), "action": one_hot(a, n_actions)}, [len(s)])


def _support_table(support: SupportEstimator, pairs: TensorDict) -> torch.Tensor:
    """Eq. (13) read out for every state-action pair: the pair's log-ratio at least the fitted threshold, up to
    float32 rounding. On one-hot inputs all samples of a pair share one log-ratio, so the kappa-quantile lands
    exactly on a pair's value; computed again in a batch of another size (another matrix-product kernel), that
    value can come out one ulp below the threshold taken from the safe samples' batch."""
    threshold = support.threshold
    tolerance = 1e-5 * torch.clamp(threshold.abs(), min=1.0)
    return (support.log_ratio(pairs.clone()).reshape(-1) >= threshold - tolerance).cpu()


def train_tabular_spoildice(
    problem: DualDemoProblem,
    config: TabularTrainingConfig | None = None,
    *,
    progress: bool = False,
    log: Callable[[dict, int], None] | None = None,
) -> TabularTrainingResult:
    """Run Algorithm 1 on samples of ``problem`` and return the learned policy's exact occupancy.

    With several constraints (``problem.d_S`` of shape ``[K, S, A]``, e.g. from
    ``random_dual_demo_problem(constraints=K)``) each constraint has its safe set, discriminator and kappa-cut,
    and :class:`SpoilDICELoss` one multiplier per constraint (``docs/several_constraints.md``);
    ``result.support`` is then the intersection of the K estimated supports.

    Args:
        problem: CMDP and distributions; D_S, D_P, D_U are ``config.n_samples`` i.i.d. draws from d_S, d_P, d_U.
        config: hyper-parameters (:class:`TabularTrainingConfig`).
        progress: show tqdm bars.
        log: called as ``log(metrics, step)`` every 100 steps of each stage.

    Examples:
        >>> from spoil_torchrl.tabular.problems import random_dual_demo_problem
        >>> cfg = TabularTrainingConfig(n_samples=2_000, n_init=100, discriminator_steps=5, dice_steps=5)
        >>> result = train_tabular_spoildice(random_dual_demo_problem(seed=0), cfg)
        >>> result.occupancy.shape, round(float(result.occupancy.sum()), 6)
        ((6, 3), 1.0)
    """
    cfg = config or TabularTrainingConfig()
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    mdp = problem.mdp
    n_s, n_a = mdp.n_states, mdp.n_actions
    history: list[dict] = []

    def record(step: int, outputs: dict[str, dict[str, float]]) -> None:  # one history line per loss
        for stage, out in outputs.items():
            metrics = {f"{stage}/{k}": v for k, v in out.items()}
            history.append({"step": step, **metrics})
            if log is not None:
                log(metrics, step)

    # Input: D_S (one per constraint: safe_<k>), D_P, D_U and the initial-state set D_0, one TorchRL buffer each.
    safe_roles = _safe_roles(problem)
    safe = [problem.d_S] if safe_roles == ["safe"] else list(problem.d_S)
    datasets = {
        role: sample_transitions(mdp, d, cfg.n_samples, rng) for role, d in zip(safe_roles, safe, strict=True)
    }
    datasets["performant"] = sample_transitions(mdp, problem.d_P, cfg.n_samples, rng)
    datasets["unlabeled"] = sample_transitions(mdp, problem.d_U, cfg.n_samples, rng)
    buffers = {role: _buffer(data, cfg.batch_size) for role, data in datasets.items()}
    buffers["init"] = _buffer(sample_initial_states(mdp, cfg.n_init, rng), cfg.batch_size)

    # Pretrain C_P and C_S (one C_S per constraint) by optimising Eq. (16) and (17).
    disc_losses = {}
    for role in ("performant", *safe_roles):
        disc = make_discriminator(n_s, n_a, hidden_cells=cfg.discriminator_cells)
        disc_losses[f"discriminator_{role}"] = PUDiscriminatorLoss(
            disc, positive=role, gradient_penalty=cfg.discriminator_gradient_penalty
        )
    disc_params = [p for loss in disc_losses.values() for p in loss.parameters()]
    disc_optim = torch.optim.Adam(disc_params, lr=cfg.discriminator_lr)
    _train_stage(
        disc_losses,
        [disc_optim],
        _sample(buffers),
        cfg.discriminator_steps,
        label="discriminators",
        progress=progress,
        record=record,
    )
    disc_losses = {name.removeprefix("discriminator_"): loss for name, loss in disc_losses.items()}

    # r_P, r_S from Eq. (18); the support indicator from Eq. (13), one per constraint; annotate D_U once.
    ratio_p = LogRatio(disc_losses["performant"].frozen_network())
    supports = [
        SupportEstimator(
            disc_losses[role].frozen_network(), kappa=cfg.kappa, out_key=_support_key(role, safe_roles)
        ).fit(datasets[role])
        for role in safe_roles
    ]
    annotate(buffers["unlabeled"], ratio_p)
    for support in supports:
        annotate(buffers["unlabeled"], support)
    if len(supports) > 1:  # the K indicators side by side, [n, K], as SpoilDICELoss(constraints=K) reads them
        keys = [support.out_keys[0] for support in supports]
        stack = TensorDictModule(lambda *xs: torch.cat(xs, -1), in_keys=keys, out_keys=["safe_support"])
        check_supports_intersect(annotate(buffers["unlabeled"], stack)["safe_support"], "safe_support")

    # Initialise nu, lambda (one per constraint), pi; then optimise Eq. (19) for (nu, lambda) and Eq. (20) for pi.
    dice = SpoilDICELoss(
        make_value_network(n_s, hidden_cells=()),
        gamma=mdp.gamma,
        gradient_penalty=cfg.nu_gradient_penalty,
        init_lagrange=cfg.init_lagrange,
        constraints=len(supports),
    )
    actor = make_actor(n_s, n_a, hidden_cells=(), distribution="categorical")
    policy_loss = WeightedBCLoss(actor, role="unlabeled", weight="dice_weight")
    nu_optim = torch.optim.Adam(dice.nu_network_params.values(True, True), lr=cfg.nu_lr)
    lagrange_optim = torch.optim.Adam([dice.lagrange], lr=cfg.lagrange_lr)
    actor_optim = torch.optim.Adam(policy_loss.parameters(), lr=cfg.actor_lr)
    _train_stage(
        {"spoildice": dice, "actor": policy_loss},
        [nu_optim, lagrange_optim, actor_optim],
        _sample({role: buffers[role] for role in ("unlabeled", "init")}),
        cfg.dice_steps,
        label="spoildice",
        progress=progress,
        record=record,
    )

    # Output: the learned policy as a table, and its exact occupancy.
    with torch.no_grad():
        states = TensorDict({"observation": one_hot(np.arange(n_s), n_s)}, [n_s])
        with policy_loss.actor_network_params.to_module(policy_loss.actor_network):
            policy = policy_loss.actor_network.get_dist(states).probs.double().numpy()
        pairs = _all_pairs(n_s, n_a)
        tables = [_support_table(support, pairs).reshape(n_s, n_a).numpy() for support in supports]
        estimated_support = np.logical_and.reduce(tables)  # with several constraints, the intersection
        log_ratio = ratio_p(pairs.clone())["log_ratio_performant"].reshape(n_s, n_a).double().numpy()
    policy = policy / policy.sum(axis=1, keepdims=True)
    return TabularTrainingResult(occupancy(mdp, policy), policy, estimated_support, log_ratio, history)


def exact_log_ratio_module(numerator: np.ndarray, denominator: np.ndarray, out_key: str) -> TensorDictModule:
    """A module writing the exact :math:`\\log(d_1(s,a)/d_2(s,a))` of two ``[S, A]`` tables at ``out_key``, for
    transitions with the integer ``state`` / ``action_index`` of :func:`sample_transitions` (in place of a
    learned discriminator's :class:`LogRatio`).

    Examples:
        >>> module = exact_log_ratio_module(np.array([[0.5, 0.5]]), np.array([[0.25, 0.75]]), "r")
        >>> td = TensorDict({"state": torch.tensor([0, 0]), "action_index": torch.tensor([0, 1])}, [2])
        >>> [round(x, 4) for x in module(td)["r"].squeeze(-1).tolist()]
        [0.6931, -0.4055]
    """
    with np.errstate(divide="ignore"):
        table = torch.as_tensor(np.log(numerator) - np.log(denominator), dtype=torch.float32)

    def lookup(state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return table[state, action].unsqueeze(-1)

    return TensorDictModule(lookup, in_keys=["state", "action_index"], out_keys=[out_key])


#: The reward key DemoDICE reads in each regularisation role (the recipe's names).
DEMODICE_REWARD_KEYS = {"safe": "log_ratio_performant_safe", "unlabeled": "log_ratio_performant"}


def train_tabular_demodice(
    problem: DualDemoProblem,
    alpha: float,
    *,
    regularization: str = "safe",
    config: TabularTrainingConfig | None = None,
    progress: bool = False,
    log: Callable[[dict, int], None] | None = None,
) -> TabularTrainingResult:
    """Train :class:`DemoDICELoss` + :class:`WeightedBCLoss` on samples of ``problem`` and return the learned
    policy's exact occupancy, to compare with ``solve_demodice(mdp, d_P, d_R, alpha)``.

    ``regularization="safe"`` is DemoDICE-S (samples of :math:`d_R = d_S`), ``"unlabeled"`` DemoDICE-U
    (:math:`d_R = d_U`). The reward :math:`\\log d_P/d_R` is annotated *exactly* from the tables
    (:func:`exact_log_ratio_module`): this checks the DICE dual and the policy extraction, not a discriminator
    (the discriminators are checked by :func:`train_tabular_spoildice`). Uses ``config``'s sample sizes,
    ``dice_steps``, ``nu_lr``, ``actor_lr``, ``nu_gradient_penalty`` and ``seed``.

    Returns:
        :class:`TabularTrainingResult` with ``support`` = :math:`supp(d_R)` and ``log_ratio_performant`` the exact
        :math:`\\log d_P/d_R` table.

    Examples:
        >>> from spoil_torchrl.tabular.problems import random_dual_demo_problem
        >>> cfg = TabularTrainingConfig(n_samples=2_000, n_init=100, dice_steps=5)
        >>> result = train_tabular_demodice(random_dual_demo_problem(seed=0), 0.1, config=cfg)
        >>> result.occupancy.shape, round(float(result.occupancy.sum()), 6)
        ((6, 3), 1.0)
    """
    if regularization not in DEMODICE_REWARD_KEYS:
        raise ValueError(
            f"regularization must be one of {tuple(DEMODICE_REWARD_KEYS)}, got {regularization!r}"
        )
    cfg = config or TabularTrainingConfig()
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    mdp = problem.mdp
    n_s, n_a = mdp.n_states, mdp.n_actions
    d_R = {"safe": problem.d_S, "unlabeled": problem.d_U}[regularization]
    reward_key = DEMODICE_REWARD_KEYS[regularization]
    history: list[dict] = []

    buffers = {
        regularization: _buffer(sample_transitions(mdp, d_R, cfg.n_samples, rng), cfg.batch_size),
        "init": _buffer(sample_initial_states(mdp, cfg.n_init, rng), cfg.batch_size),
    }
    ratio = exact_log_ratio_module(problem.d_P, d_R, reward_key)
    annotate(buffers[regularization], ratio)

    dice = DemoDICELoss(
        make_value_network(n_s, hidden_cells=()),
        alpha=alpha,
        gamma=mdp.gamma,
        gradient_penalty=cfg.nu_gradient_penalty,
        regularization=regularization,
        reward=reward_key,
    )
    actor = make_actor(n_s, n_a, hidden_cells=(), distribution="categorical")
    policy_loss = WeightedBCLoss(actor, role=regularization, weight="dice_weight")

    def record(step: int, outputs: dict[str, dict[str, float]]) -> None:  # one history line per step
        metrics = {f"{stage}/{k}": v for stage, out in outputs.items() for k, v in out.items()}
        history.append({"step": step, **metrics})
        if log is not None:
            log(metrics, step)

    optimizers = [
        torch.optim.Adam(dice.parameters(), lr=cfg.nu_lr),
        torch.optim.Adam(policy_loss.parameters(), lr=cfg.actor_lr),
    ]
    _train_stage(
        {"demodice": dice, "actor": policy_loss},
        optimizers,
        _sample(buffers),
        cfg.dice_steps,
        label="demodice",
        progress=progress,
        record=record,
    )

    with torch.no_grad():
        states = TensorDict({"observation": one_hot(np.arange(n_s), n_s)}, [n_s])
        with policy_loss.actor_network_params.to_module(policy_loss.actor_network):
            policy = policy_loss.actor_network.get_dist(states).probs.double().numpy()
    policy = policy / policy.sum(axis=1, keepdims=True)
    with np.errstate(divide="ignore"):
        log_ratio = np.log(problem.d_P) - np.log(d_R)
    return TabularTrainingResult(occupancy(mdp, policy), policy, d_R > 0, log_ratio, history)
