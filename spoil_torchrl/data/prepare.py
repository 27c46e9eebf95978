"""From a dataset source to the inputs of Algorithm 1: D_S, D_P, D_U episode ids, the task, the cost threshold
and the return normalisation (paper F.1 for IL-SP labelling, F.2 for controlled mixes)."""

from __future__ import annotations

import hashlib
import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import PurePath

import torch
from tensordict import TensorDict

from spoil_torchrl.data.collect import segment_pools
from spoil_torchrl.data.constraint_costs import constraint_roles
from spoil_torchrl.data.episodes import DatasetError
from spoil_torchrl.data.generated import ensure_generated
from spoil_torchrl.data.labeling import (
    controlled_mix,
    corrupt,
    draw,
    episode_stats,
    label_ilsp,
    replay_subsets,
)
from spoil_torchrl.data.load import load_episodes, parse_source, read_source_metadata
from spoil_torchrl.files import update_digest
from spoil_torchrl.stack import current_stack, stack_differences, stack_label
from spoil_torchrl.tasks import ENV_TASKS, get_dsrl_dataset

SCHEMES = ("ilsp", "controlled", "replay", "stored")
EXTRA_ROLES = ("nonpreferred",)


@dataclass
class PreparedDataset:
    """A loaded dataset with its roles and the constants to evaluate on it."""

    episodes: TensorDict
    roles: dict[str, torch.Tensor]
    env_id: str
    cost_threshold: float
    return_range: tuple[float, float]
    metadata: dict = field(default_factory=dict)

    def fingerprint(self) -> str:
        """SHA-256 (16 hex digits) of every stored transition, whatever file or format they came from.

        Examples:
            >>> episodes = TensorDict({"observation": torch.zeros(2, 1)}, [2])
            >>> a = PreparedDataset(episodes, {}, "SafetyPointCircle1-v0", 25.0, (0.0, 1.0)).fingerprint()
            >>> episodes["observation"][0] = 1.0
            >>> a == PreparedDataset(episodes, {}, "SafetyPointCircle1-v0", 25.0, (0.0, 1.0)).fingerprint()
            False
        """
        digest = hashlib.sha256()
        for key in sorted(self.episodes.keys(include_nested=True, leaves_only=True), key=str):
            update_digest(digest, str(key), self.episodes.get(key))
        return digest.hexdigest()[:16]

    def summary(self) -> dict:
        """Sizes of the roles (episodes and transitions) and the constants, for logs and ``results.json``."""
        stats = episode_stats(self.episodes)
        out = {
            "env_id": self.env_id,
            "cost_threshold": self.cost_threshold,
            "return_range": self.return_range,
            "stack": self.metadata.get("stack"),  # what the data were made on (None: not recorded)
            "fingerprint": self.fingerprint(),  # which data: the report never averages runs of different data
        }
        for role, ids in self.roles.items():
            out[role] = {
                "episodes": int(ids.numel()),
                "transitions": int(stats["length"][ids].sum()),
                "mean_return": float(stats["return"][ids].mean()),
                "mean_cost": float(stats["cost"][ids].mean()),
                "safe_share": float((stats["cost"][ids] <= self.cost_threshold).double().mean()),
            }
        return out


def _source_constants(source: str, metadata: dict) -> tuple[str | None, float | None, tuple | None]:
    """(env_id, cost threshold, return range) a source implies: its metadata or the DSRL table."""
    scheme, rest = parse_source(source)
    if scheme == "dsrl":
        d = get_dsrl_dataset(rest)
        env = next((t.env_id for t in ENV_TASKS.values() if t.dsrl_id == d.dataset_id), None)
        return env, d.cost_threshold, (d.min_return, d.max_return)
    if metadata.get("random_return") is not None and metadata.get("safe_high_return") is not None:
        rng = (metadata["random_return"], metadata["safe_high_return"])
    else:  # a Minari dataset's reference scores, when it has them
        rng = metadata.get("return_range")
    return metadata.get("env_id"), metadata.get("cost_threshold"), rng


def _check_action_bounds(actions: torch.Tensor, task, source: str) -> None:
    """Refuse actions outside the task's box: the policies cannot produce them (tanh-squashed), so training
    on them is fitting values no policy can take (and their log-likelihoods explode)."""
    bound = task.action_bound * (1 + 1e-6)  # float rounding of a clipped action
    outside = actions.abs() > bound
    if bool(outside.any()):
        row, column = (int(i) for i in outside.nonzero()[0])
        raise DatasetError(
            f"{source}: {int(outside.sum())} action values lie outside {task.env_id}'s bounds "
            f"[-{task.action_bound:g}, {task.action_bound:g}] (first: {float(actions[row, column]):.4g} at row "
            f"{row}, column {column}); rescale the actions to the task's bounds"
        )


def select_roles(
    episodes: TensorDict,
    cfg: Mapping,
    *,
    cost_threshold: float,
    metadata: Mapping,
    seed: int,
    extra_roles: Sequence[str] = (),
) -> dict[str, torch.Tensor]:
    """D_S, D_P, D_U (and the ``extra_roles`` an algorithm asks for) as episode ids, by ``cfg["scheme"]``:

    * ``"ilsp"`` (F.1): label every episode (safe iff cost <= threshold; performant iff return >= the
      ``return_quantile`` quantile of the safe returns), then draw ``n_safe`` safe and ``n_performant``
      performant episodes (seeded); D_U = every episode, or ``n_unlabeled`` drawn ones. The two draws are
      independent: an episode that is both safe and performant may be in both (F.1's labels overlap).
    * ``"controlled"`` (F.2): :func:`~spoil_torchrl.data.controlled_mix` of the file's policy-type pools with
      ``performance`` (share of safe-high in D_S) and ``safeness`` (share of safe-high in D_P); the safe types'
      trajectories in D_S and D_P are episodes within ``cost_threshold``, the unsafe types' episodes over it.
    * ``"replay"`` (F.2, Table K): one trajectory buffer of an expert's training labelled as the paper does
      (safe iff cost <= threshold; performant iff return >= ``return_fraction`` (0.9) of the safe-optimal
      return), then drawn as for ``"ilsp"``: ``n_safe`` safe, ``n_performant`` performant, ``n_unlabeled``
      of all.
    * ``"stored"``: the roles stored with the data (``metadata["roles"]``: episode ids per role, e.g. a Minari
      dataset exported with its roles or labelled by hand with ``role_safe`` / ``role_performant`` /
      ``role_unlabeled`` episode flags); ``seed`` and the ``n_*`` sizes do not apply.

    ``cfg["constraints"]`` (names of the data's per-constraint costs, ``docs/several_constraints.md``) adds one
    safe set per constraint, the roles ``safe_<name>`` (:func:`~spoil_torchrl.data.constraint_costs.constraint_roles`);
    with ``cfg["constraint_pools"]`` (scheme ``"controlled"``) each is D_S with episodes of one typed pool.

    ``cfg["corruption"]`` (default 0) makes D_S noisy as the paper's G.6 does: that share of its trajectories is
    replaced by unsafe ones (episode cost above ``cost_threshold``) drawn from D_U outside D_S and D_P (seeded).

    ``extra_roles`` may hold ``"nonpreferred"`` (D_N, for SafeDICE): the *unsafe* episodes of D_U (episode
    cost above ``cost_threshold``, F.1's non-preferred label), all of them (the paper, section 5.2.1: "we use
    the entire set of unsafe demonstrations as non-preferred") or ``cfg["n_nonpreferred"]`` drawn ones
    (seeded) when set, in either scheme. Taking them from D_U keeps SafeDICE's assumption that D_U mixes D_N
    with the preferred data. Other algorithms do not ask for it, so their buffers never sample it.
    """
    scheme = cfg["scheme"]
    if scheme not in SCHEMES:
        raise ValueError(f"unknown labelling scheme {scheme!r}; choose one of {SCHEMES}")
    unknown = [role for role in extra_roles if role not in EXTRA_ROLES]
    if unknown:
        raise ValueError(f"unknown extra roles {unknown}; available: {EXTRA_ROLES}")
    roles = _base_roles(episodes, cfg, cost_threshold=cost_threshold, metadata=metadata, seed=seed)
    if cfg.get("constraint_pools") and cfg.get("constraints") and float(cfg.get("corruption") or 0.0) != 0.0:
        raise DatasetError(
            "dataset.constraint_pools with dataset.corruption: each constraint's safe set holds D_S, which the "
            "corruption would change after the sets are drawn; use one of them"
        )
    typed = segment_pools(dict(metadata)) if cfg.get("constraint_pools") and scheme == "controlled" else None
    roles |= constraint_roles(
        episodes, cfg, cost_threshold=cost_threshold, seed=seed, safe=roles["safe"], pools=typed
    )
    if float(cfg.get("corruption") or 0.0) != 0.0:
        roles["safe"] = _corrupted_safe(episodes, roles, float(cfg["corruption"]), cost_threshold, seed)
    if "nonpreferred" in extra_roles:
        roles["nonpreferred"] = _nonpreferred(episodes, roles["unlabeled"], cfg, cost_threshold, seed)
    return roles


def _corrupted_safe(
    episodes: TensorDict, roles: dict[str, torch.Tensor], rate: float, cost_threshold: float, seed: int
) -> torch.Tensor:
    """D_S with the share ``rate`` of its trajectories replaced by unsafe episodes of D_U that are in neither D_S
    nor D_P (noisy safe demonstrations, G.6), see :func:`select_roles`."""
    if not 0.0 <= rate < 1.0:
        raise DatasetError(f"dataset.corruption = {rate}: expected a share in [0, 1)")
    cost = episode_stats(episodes)["cost"]
    taken = torch.cat([roles["safe"], roles["performant"]])
    candidates = roles["unlabeled"][~torch.isin(roles["unlabeled"], taken)]
    unsafe = candidates[cost[candidates] > cost_threshold]
    needed = round(rate * roles["safe"].numel())
    if unsafe.numel() < needed:
        raise DatasetError(
            f"dataset.corruption={rate} replaces {needed} of D_S's {roles['safe'].numel()} trajectories, but D_U "
            f"has {unsafe.numel()} unsafe episodes outside D_S and D_P; lower the corruption or n_safe"
        )
    return corrupt(roles["safe"], unsafe, rate, seed=seed + 5)


def _nonpreferred(
    episodes: TensorDict, unlabeled: torch.Tensor, cfg: Mapping, cost_threshold: float, seed: int
) -> torch.Tensor:
    """The unsafe episodes of D_U (all, or ``cfg["n_nonpreferred"]`` drawn), see :func:`select_roles`."""
    cost = episode_stats(episodes)["cost"]
    unsafe = unlabeled[cost[unlabeled] > cost_threshold]
    if unsafe.numel() == 0:
        raise DatasetError(
            f"D_U has no unsafe episode (cost above {cost_threshold}): SafeDICE has no non-preferred data"
        )
    k = cfg.get("n_nonpreferred")
    if k is None:
        return torch.sort(unsafe).values
    if unsafe.numel() < int(k):
        raise DatasetError(
            f"D_U has {unsafe.numel()} unsafe episodes, fewer than n_nonpreferred={k}; lower n_nonpreferred"
        )
    return draw(unsafe, int(k), seed=seed + 3)


def _stored_roles(metadata: Mapping, n_episodes: int) -> dict[str, torch.Tensor]:
    """D_S, D_P, D_U as stored with the data (``metadata["roles"]``), see :func:`select_roles`."""
    stored = metadata.get("roles") or {}
    missing = [role for role in ("safe", "performant", "unlabeled") if role not in stored]
    if missing:
        raise DatasetError(
            f"dataset.scheme=stored, but the dataset stores no {missing[0]!r} role (it has "
            f"{sorted(stored) or 'none'}); export it with its roles (recipes/export_minari.py) or use "
            "scheme=ilsp / controlled"
        )
    try:
        roles = {
            role: torch.as_tensor(stored[role], dtype=torch.int64)
            for role in ("safe", "performant", "unlabeled")
        }
    except (TypeError, ValueError, RuntimeError) as err:
        raise DatasetError(f"the stored roles are not lists of episode ids ({err})") from None
    empty = [role for role, ids in roles.items() if ids.numel() == 0]
    if empty:
        raise DatasetError(f"the stored role {empty[0]!r} has no episode")
    for role, ids in roles.items():
        if ids.ndim != 1 or bool(((ids < 0) | (ids >= n_episodes)).any()):
            raise DatasetError(
                f"the stored role {role!r} names episodes outside the dataset's {n_episodes} (ids "
                f"{ids.reshape(-1)[:5].tolist()}...); the roles belong to another file"
            )
    return roles


def _base_roles(
    episodes: TensorDict, cfg: Mapping, *, cost_threshold: float, metadata: Mapping, seed: int
) -> dict[str, torch.Tensor]:
    """D_S, D_P, D_U of ``cfg["scheme"]`` (see :func:`select_roles`)."""
    scheme = cfg["scheme"]
    n_unlabeled = cfg.get("n_unlabeled")
    if scheme == "stored":
        return _stored_roles(metadata, int(episodes["episode"].max()) + 1)
    if scheme == "controlled":
        try:
            pools = segment_pools(dict(metadata))
        except ValueError as err:
            raise DatasetError(
                f"{cfg['source']}: dataset.scheme=controlled needs the typed pools of a collected file ({err}); "
                "use scheme=ilsp"
            ) from None
        try:
            return controlled_mix(
                pools,
                n_safe=int(cfg["n_safe"]),
                performance=float(cfg["performance"]),
                n_performant=int(cfg["n_performant"]),
                safeness=float(cfg["safeness"]),
                n_unlabeled=None if n_unlabeled is None else int(n_unlabeled),
                seed=seed,
                episode_cost=episode_stats(episodes)["cost"],
                cost_limit=cost_threshold,
            )
        except ValueError as err:  # sizes the pools cannot give
            raise DatasetError(
                f"{cfg['source']}: {err} (dataset.n_safe={cfg['n_safe']}, n_performant={cfg['n_performant']}, "
                f"n_unlabeled={n_unlabeled}); lower the sizes"
            ) from None
    if scheme == "replay":
        labels = _replay_labels(episodes, cfg, cost_threshold, metadata)
    else:
        try:
            labels = label_ilsp(episodes, cost_threshold, float(cfg.get("return_quantile", 0.9)))
        except DatasetError as err:
            raise DatasetError(f"{cfg['source']}: {err} (or raise dataset.cost_threshold)") from None
    roles = {}
    for role, key, offset in (("safe", "n_safe", 0), ("performant", "n_performant", 1)):
        ids, k = labels[role], int(cfg[key])
        if ids.numel() < k:
            how = (
                f"cost threshold {cost_threshold}"
                if role == "safe"
                else f"scheme {scheme}'s return threshold"
            )
            raise DatasetError(
                f"the dataset has {ids.numel()} {role} episodes ({how}), fewer than {key}={k}; lower {key}"
            )
        roles[role] = draw(ids, k, seed=seed + offset)
    unlabeled = labels["unlabeled"]
    if n_unlabeled is not None and int(n_unlabeled) > unlabeled.numel():
        raise DatasetError(
            f"the dataset has {unlabeled.numel()} episodes, fewer than n_unlabeled={n_unlabeled}; lower "
            "n_unlabeled (null: every episode)"
        )
    roles["unlabeled"] = (
        unlabeled if n_unlabeled is None else draw(unlabeled, int(n_unlabeled), seed=seed + 2)
    )
    return roles


def _replay_labels(episodes: TensorDict, cfg: Mapping, cost_threshold: float, metadata: Mapping) -> dict:
    """F.2's labels of a replay buffer (:func:`~spoil_torchrl.data.replay_subsets`): safe iff the episode cost
    is within ``cost_threshold``, performant iff the return reaches ``return_fraction`` (0.9) of the
    safe-optimal return (``dataset.return_range``'s R_max, else the file's ``safe_high_return``)."""
    given = cfg.get("return_range")
    optimal = float(given[1]) if given is not None else metadata.get("safe_high_return")
    if optimal is None:
        raise DatasetError(
            f"{cfg['source']}: dataset.scheme=replay needs the safe-optimal return (the file's safe_high_return, "
            "or dataset.return_range=[R_min,R_max])"
        )
    return replay_subsets(episodes, cost_threshold, float(optimal), float(cfg.get("return_fraction", 0.9)))


def prepare_dataset(
    cfg: Mapping,
    *,
    env_id: str | None = None,
    seed: int = 0,
    progress: bool = True,
    extra_roles: Sequence[str] = (),
) -> PreparedDataset:
    """Load ``cfg["source"]`` (making a named generated dataset first when ``cfg["generate"]`` and it is not
    cached), work out the cost threshold and return range (``cfg`` overrides, else the file's metadata or the
    DSRL table), check that it belongs to ``env_id``, and select the roles (:func:`select_roles`, with the
    ``extra_roles`` the algorithm needs, e.g. ``("nonpreferred",)`` for SafeDICE)."""
    source = cfg["source"]
    scheme, rest = parse_source(source)
    if scheme == "generated" and cfg.get("generate", True):
        ensure_generated(rest, progress=progress)
    episodes = load_episodes(source, progress=progress)
    metadata = read_source_metadata(source)
    if metadata.get("stack") is not None and stack_differences(metadata["stack"]):
        warnings.warn(
            f"{source} was made on another software stack ({stack_label(metadata['stack'])}; here "
            f"{stack_label(current_stack())}): its episodes come from other physics than this run's "
            "evaluations (results.json records both stacks; spoil-report flags the run)",
            stacklevel=2,
        )
    source_env, source_threshold, source_range = _source_constants(source, metadata)
    if env_id is not None and source_env is not None and source_env != env_id:
        raise DatasetError(f"dataset {source} was recorded in {source_env}, but the task is {env_id}")
    threshold = cfg.get("cost_threshold") if cfg.get("cost_threshold") is not None else source_threshold
    return_range = cfg.get("return_range") if cfg.get("return_range") is not None else source_range
    if threshold is None:
        raise DatasetError(f"{source}: no cost threshold known; set dataset.cost_threshold")
    if return_range is None:
        raise DatasetError(f"{source}: no return range known; set dataset.return_range=[R_min,R_max]")
    try:
        low, high = (float(v) for v in return_range)
        ok = math.isfinite(low) and math.isfinite(high) and low < high
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise DatasetError(
            f"{source}: its metadata gives the return range {return_range!r}, not two finite numbers R_min < "
            "R_max; set dataset.return_range=[R_min,R_max]"
        )
    if not (isinstance(threshold, (int, float)) and math.isfinite(threshold) and threshold >= 0):
        raise DatasetError(
            f"{source}: its metadata gives the cost threshold {threshold!r}; set dataset.cost_threshold"
        )
    task = ENV_TASKS.get(env_id or source_env or "")
    obs_dim, act_dim = episodes["observation"].shape[-1], episodes["action"].shape[-1]
    if task is not None and (obs_dim, act_dim) != (task.observation_dim, task.action_dim):
        raise DatasetError(
            f"{source}: observation/action sizes {obs_dim}/{act_dim}, but {task.env_id} has "
            f"{task.observation_dim}/{task.action_dim}: the data belong to another task (set task=...)"
        )
    if task is not None:
        _check_action_bounds(episodes["action"], task, source)
    roles = select_roles(
        episodes, cfg, cost_threshold=float(threshold), metadata=metadata, seed=seed, extra_roles=extra_roles
    )
    return PreparedDataset(
        episodes,
        roles,
        env_id or source_env,
        float(threshold),
        (float(return_range[0]), float(return_range[1])),
        metadata,
    )


def source_name(source: str) -> str:
    """A dataset name made from its source, for a run whose ``dataset.source`` was set without a
    ``dataset.name``: the file's stem, or the id after the scheme.

    Examples:
        >>> source_name("file:/data/pc1-noisy.hdf5"), source_name("dsrl:OfflinePointCircle1Gymnasium-v0")
        ('pc1-noisy', 'OfflinePointCircle1Gymnasium-v0')
    """
    scheme, _, rest = source.partition(":")
    if scheme == "file" or not rest:
        return PurePath(rest or source).stem
    return rest
