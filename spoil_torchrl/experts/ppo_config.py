"""The settings of an expert's PPO / PPO-Lagrangian training (:func:`~spoil_torchrl.experts.train_ppo`), checked
when they are made, so that a bad value is refused before anything is written."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from spoil_torchrl.envs.path_reward import check_half_axes


@dataclass
class PPOConfig:
    """Hyper-parameters of :func:`train_ppo` (defaults: common PPO settings for Safety-Gymnasium tasks).

    ``record_episodes`` > 0 keeps that many of every batch's finished episodes in a trajectory buffer
    (``replay/``, :class:`~spoil_torchrl.experts.replay.ReplayRecorder`): the replay datasets of the paper's F.2.
    ``normalize_observations`` puts a running standardisation of the observations in front of the actor and
    both critics (OmniSafe's ``obs_normalize``): the statistics of every batch so far, fixed within a batch
    (updated after its PPO update, so a batch's log-probabilities are computed with the statistics it was
    collected with), saved inside the policy (:func:`~spoil_torchrl.modules.with_observation_norm`).
    Three of OmniSafe's PPO-Lagrangian settings are options (off by default, as the committed experts were
    trained): ``advantage_standardization="separate"`` standardises the reward and the cost advantages each on
    its own before they are combined (``"combined"``: the combined one); ``target_kl`` stops a batch's epochs
    early once the policy's estimated KL divergence from the one that collected it passes it (OmniSafe: 0.02);
    ``lr_decay`` lowers the actor's learning rate linearly to 0 over the run.
    ``cost_penalty`` > 0 (with ``lagrangian=False``) trains on the reward minus ``cost_penalty`` times the cost,
    a fixed multiplier where PPO-Lagrangian adapts one: a demonstrator that keeps the constraint by a penalty.
    ``cost_component`` (with ``num_envs`` > 1) trains against one constraint's own cost instead of the task's
    (:mod:`spoil_torchrl.envs.cost_components`, e.g. ``x_wall`` in SafetyPointCircle2): a demonstrator safe on
    that constraint only.
    ``track_ellipse`` ``[a, b]`` (with ``num_envs`` > 1, in a circle task) trains on the task's reward for an
    ellipse with those half-axes instead of its circle (:mod:`spoil_torchrl.envs.path_reward`): a demonstrator
    that keeps one pair of SafetyPointCircle2's walls and crosses the other by design.
    ``init_actor`` starts the actor from a policy instead of at random (fine-tuning; the critics start afresh):
    a policy or PPO checkpoint file, or ``zoo:<name>`` for a committed policy of the task, with the same
    ``hidden_cells``, without observation standardisation. E.g. a demonstrator that keeps one constraint only, tuned
    from the unconstrained expert with a penalty on that constraint's cost (``docs/several_constraints.md``).
    ``num_envs`` > 1 collects each batch from that many environments stepped in lockstep
    (:class:`~spoil_torchrl.experts.lockstep.LockstepCollector`: several times the frames per second of one
    TorchRL environment); ``frames_per_batch`` must split evenly over them.

    Examples:
        >>> config = PPOConfig(total_frames=800_000, lagrangian=True, num_envs=8, hidden_cells=[64, 64])
        >>> config.cost_limit, config.frames_per_batch // config.num_envs, config.hidden_cells
        (25.0, 1250, (64, 64))
        >>> PPOConfig(frames_per_batch=2000, minibatch_size=4000)
        Traceback (most recent call last):
        ...
        ValueError: ppo.minibatch_size = 4000 is larger than ppo.frames_per_batch = 2000
        >>> PPOConfig(lagrangian=True, cost_penalty=1.0)
        Traceback (most recent call last):
        ...
        ValueError: ppo.cost_penalty = 1.0 with ppo.lagrangian=true: PPO-Lagrangian learns its multiplier; a \
fixed penalty needs ppo.lagrangian=false
    """

    total_frames: int = 1_000_000
    frames_per_batch: int = 10_000
    epochs: int = 10
    minibatch_size: int = 1000
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_epsilon: float = 0.2
    actor_lr: float = 3e-4
    critic_lr: float = 1e-3
    entropy_coeff: float = 0.0
    max_grad_norm: float = 0.5
    hidden_cells: tuple[int, ...] = (64, 64)
    lagrangian: bool = False
    cost_limit: float = 25.0
    lagrange_lr: float = 0.035
    lagrange_init: float = 0.0
    cost_penalty: float = 0.0
    cost_component: str | None = None
    track_ellipse: tuple[float, float] | None = None
    checkpoint_every: int = 5  # batches
    normalize_observations: bool = False
    record_episodes: int = 0
    num_envs: int = 1
    advantage_standardization: str = "combined"
    target_kl: float | None = None
    lr_decay: bool = False
    init_actor: str | None = None
    seed: int = 0
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in (
            "total_frames",
            "frames_per_batch",
            "epochs",
            "minibatch_size",
            "checkpoint_every",
            "num_envs",
        ):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"ppo.{name} = {value!r}: expected an integer >= 1")
        if self.minibatch_size > self.frames_per_batch:
            raise ValueError(
                f"ppo.minibatch_size = {self.minibatch_size} is larger than ppo.frames_per_batch = "
                f"{self.frames_per_batch}"
            )
        if self.advantage_standardization not in ("combined", "separate"):
            raise ValueError(
                f"ppo.advantage_standardization = {self.advantage_standardization!r}: expected combined or separate"
            )
        if self.target_kl is not None and (
            isinstance(self.target_kl, bool)
            or not isinstance(self.target_kl, (int, float))
            or not math.isfinite(self.target_kl)
            or self.target_kl <= 0
        ):
            raise ValueError(f"ppo.target_kl = {self.target_kl!r}: expected null or a finite number > 0")
        for name in ("lagrangian", "normalize_observations", "lr_decay"):  # Hydra keeps "no" as a string
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"ppo.{name} = {getattr(self, name)!r}: expected true or false")
        for name in (
            "gamma",
            "gae_lambda",
            "clip_epsilon",
            "actor_lr",
            "critic_lr",
            "max_grad_norm",
            "lagrange_lr",
        ):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not math.isfinite(value)
                or value <= 0
            ):
                raise ValueError(f"ppo.{name} = {value!r}: expected a finite number > 0")
        penalty = self.cost_penalty
        if isinstance(penalty, bool) or not isinstance(penalty, (int, float)) or not 0 <= penalty < math.inf:
            raise ValueError(f"ppo.cost_penalty = {penalty!r}: expected a finite number >= 0")
        if penalty and self.lagrangian:
            raise ValueError(
                f"ppo.cost_penalty = {penalty} with ppo.lagrangian=true: PPO-Lagrangian learns its multiplier; "
                "a fixed penalty needs ppo.lagrangian=false"
            )
        for name, what in (
            ("cost_component", "each constraint's cost"),
            ("track_ellipse", "the agent's position"),
        ):
            if getattr(self, name) is not None and self.num_envs == 1:
                raise ValueError(
                    f"ppo.{name} = {getattr(self, name)!r} needs ppo.num_envs > 1 (the lockstep collector reads "
                    f"{what} from the simulator)"
                )
        if self.track_ellipse is not None:
            self.track_ellipse = check_half_axes(self.track_ellipse)
        if self.init_actor is not None and self.normalize_observations:
            raise ValueError(
                "ppo.init_actor with ppo.normalize_observations=true: the running statistics would start afresh "
                "under a policy tuned to others; fine-tune without observation standardisation"
            )
        if self.frames_per_batch % self.num_envs:
            raise ValueError(
                f"ppo.frames_per_batch = {self.frames_per_batch} does not split over ppo.num_envs = {self.num_envs}"
            )
        if not isinstance(self.record_episodes, int) or self.record_episodes < 0:
            raise ValueError(f"ppo.record_episodes = {self.record_episodes!r}: expected an integer >= 0")
        self.hidden_cells = tuple(self.hidden_cells)
