"""Policy checkpoints: save / load a Gaussian actor with the facts needed to rebuild it, and the committed zoo.

A policy file is a plain dict that ``torch.load(..., weights_only=True)`` accepts::

    {"format": 1, "env_id": "SafetyPointCircle1-v0", "hidden_cells": [64, 64],
     "observation_dim": 28, "action_dim": 2, "distribution": "tanh_normal", "observation_norm": False,
     "actor": <state_dict>, "info": {...}}

With ``"observation_norm": True`` the actor standardises its raw observations itself: its state dict holds an
:class:`~spoil_torchrl.modules.ObservationNormalizer`'s ``loc`` / ``scale`` in front of the MLP
(:func:`~spoil_torchrl.modules.with_observation_norm`), and :func:`load_policy` rebuilds it so.

:func:`load_policy` also reads the raw ``ckpt_<frames>.pt`` files that :func:`~spoil_torchrl.experts.train_ppo`
writes (``{"actor": <state_dict>, "frames": ..., ...}``): the layer sizes are then read off the weights.

The **zoo** is the set of policies committed with the package (``spoil_torchrl/zoo/<env_id>/<name>.pt``):
the paper's four policy types (``safe-high``, ``safe-medium``, ``unsafe-high``, ``unsafe-medium``) and a few
intermediate PPO / PPO-Lagrangian checkpoints, from which :mod:`spoil_torchrl.data.generated` makes datasets.
``docs/experts.md`` says where each one comes from and how it scores.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import torch
from torchrl.modules import ProbabilisticActor

from spoil_torchrl.files import save_atomic, update_digest
from spoil_torchrl.modules import (
    ObservationNormalizer,
    make_actor,
    observation_normalizer_of,
    with_observation_norm,
)

POLICY_FORMAT = 1
ZOO_DIR = Path(__file__).parent  #: spoil_torchrl/zoo/<env_id>/<name>.pt


class PolicyFileError(ValueError):
    """A policy file that cannot be loaded (missing, not a checkpoint, wrong task or sizes).

    Examples:
        >>> path = zoo_policy("SafetyPointCircle1-v0", "safe-high")
        >>> try:
        ...     load_policy(path, env_id="SafetyHopperVelocity-v1")
        ... except PolicyFileError as err:
        ...     print(str(err).split(": ", 1)[1])
        a policy for SafetyPointCircle1-v0, not SafetyHopperVelocity-v1
    """


def _linear_weights(state_dict: dict) -> list[torch.Tensor]:
    return [v for k, v in state_dict.items() if k.endswith("weight") and v.ndim == 2]


def _sizes_from_weights(state_dict: dict) -> tuple[int, tuple[int, ...], int]:
    """(observation_dim, hidden_cells, action_dim) of a :func:`make_actor` Gaussian MLP's state dict."""
    weights = _linear_weights(state_dict)
    if not weights:
        raise PolicyFileError("the state dict has no linear layers")
    hidden = tuple(int(w.shape[0]) for w in weights[:-1])
    out = int(weights[-1].shape[0])
    if out % 2:
        raise PolicyFileError(f"the last layer has {out} outputs; a Gaussian actor has 2 x action_dim")
    return int(weights[0].shape[1]), hidden, out // 2


def weights_digest(state: dict[str, torch.Tensor]) -> str:
    """SHA-256 over a state dict's names, dtypes, shapes and bytes (stored in policy files, checked on load)."""
    digest = hashlib.sha256()
    for key in sorted(state):
        update_digest(digest, key, state[key])
    return digest.hexdigest()


def save_policy(
    path: str | os.PathLike,
    actor: ProbabilisticActor,
    *,
    env_id: str,
    distribution: str = "tanh_normal",
    info: dict | None = None,
) -> Path:
    """Write ``actor`` (built by :func:`~spoil_torchrl.modules.make_actor` with ``distribution``, possibly
    wrapped by :func:`~spoil_torchrl.modules.with_observation_norm`) as a policy file (atomically).

    ``info`` is free JSON-like data kept with the weights (e.g. the training run and frame count).

    Examples:
        >>> import tempfile
        >>> actor = make_actor(28, 2, hidden_cells=(8,))
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     path = save_policy(f"{tmp}/p.pt", actor, env_id="SafetyPointCircle1-v0", info={"frames": 5})
        ...     loaded, meta = load_policy(path)
        >>> meta["hidden_cells"], meta["info"]
        ([8], {'frames': 5})
    """
    state = {k: v.detach().cpu().clone() for k, v in actor.state_dict().items()}
    obs_dim, hidden, act_dim = _sizes_from_weights(state)
    path = Path(path)
    save_atomic(
        {
            "format": POLICY_FORMAT,
            "env_id": env_id,
            "observation_dim": obs_dim,
            "action_dim": act_dim,
            "hidden_cells": list(hidden),
            "distribution": distribution,
            "observation_norm": observation_normalizer_of(actor) is not None,
            "actor": state,
            "weights_sha256": weights_digest(state),
            "info": dict(info or {}),
        },
        path,
    )
    return path


def load_policy(path: str | os.PathLike, *, env_id: str | None = None) -> tuple[ProbabilisticActor, dict]:
    """Rebuild the actor stored at ``path`` (a policy file or a raw PPO checkpoint), in eval mode.

    Args:
        path: the file.
        env_id: if given, the policy must be for this task (checked against the file's ``env_id`` when it has
            one, and against the task's observation / action sizes always).

    Returns:
        ``(actor, meta)`` with ``meta`` holding ``env_id`` (or ``None``), the sizes, ``hidden_cells``,
        ``observation_norm`` (whether the actor standardises its raw observations itself) and ``info``.

    Raises:
        PolicyFileError: missing or unreadable file, damaged weights (checksum mismatch, files written by
            :func:`save_policy`; non-finite values, any file), or a policy for another task.

    Examples:
        >>> from tensordict import TensorDict
        >>> path = zoo_policy("SafetyPointCircle1-v0", "safe-high")
        >>> actor, meta = load_policy(path, env_id="SafetyPointCircle1-v0")
        >>> meta["env_id"], meta["observation_dim"], meta["action_dim"], meta["hidden_cells"]
        ('SafetyPointCircle1-v0', 28, 2, [64, 64])
        >>> action = actor(TensorDict({"observation": torch.zeros(5, 28)}, [5]))["action"]
        >>> action.shape, bool(action.abs().max() <= 1)  # a batch of actions in the task's bounds
        (torch.Size([5, 2]), True)
    """
    path = Path(path)
    if not path.is_file():
        raise PolicyFileError(f"{path}: no such policy file")
    try:
        raw = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises several types for corrupt / foreign pickles
        raise PolicyFileError(f"{path}: not a policy checkpoint ({type(err).__name__}: {err})") from err
    if not isinstance(raw, dict) or not isinstance(raw.get("actor"), dict):
        raise PolicyFileError(f"{path}: not a policy checkpoint (no 'actor' state dict)")
    state = raw["actor"]
    if "weights_sha256" in raw and weights_digest(state) != raw["weights_sha256"]:
        raise PolicyFileError(f"{path}: the weights do not match their checksum (the file is damaged)")
    bad = [k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise PolicyFileError(f"{path}: non-finite weights in {', '.join(bad[:3])}")
    obs_dim, hidden, act_dim = _sizes_from_weights(state)
    meta = {
        "env_id": raw.get("env_id"),
        "observation_dim": obs_dim,
        "action_dim": act_dim,
        "hidden_cells": list(hidden),
        "distribution": raw.get("distribution", "tanh_normal"),
        "observation_norm": bool(raw.get("observation_norm", False)),
        "info": raw.get("info", {k: v for k, v in raw.items() if k != "actor"}),
    }
    if env_id is not None:
        from spoil_torchrl.tasks import get_env_task

        task = get_env_task(env_id)
        if meta["env_id"] is not None and meta["env_id"] != env_id:
            raise PolicyFileError(f"{path}: a policy for {meta['env_id']}, not {env_id}")
        if (obs_dim, act_dim) != (task.observation_dim, task.action_dim):
            raise PolicyFileError(
                f"{path}: a policy for observation/action sizes {obs_dim}/{act_dim}; {env_id} has "
                f"{task.observation_dim}/{task.action_dim}"
            )
    # the random initial weights are replaced below: building them must not advance the caller's generator
    # (a run that makes its dataset first would otherwise train from other initial weights than one that finds
    # it cached)
    with torch.random.fork_rng(devices=[]):
        actor = make_actor(obs_dim, act_dim, hidden_cells=hidden, distribution=meta["distribution"])
    if meta["observation_norm"]:
        actor = with_observation_norm(actor, ObservationNormalizer.identity(obs_dim))
    try:
        actor.load_state_dict(state)
    except RuntimeError as err:
        raise PolicyFileError(
            f"{path}: the weights do not fit a {meta['distribution']} actor ({err})"
        ) from err
    norm = observation_normalizer_of(actor)
    if norm is not None:
        try:
            norm.validate()
        except ValueError as err:
            raise PolicyFileError(f"{path}: the observation statistics are invalid ({err})") from err
    return actor.eval(), meta


def export_checkpoint(
    checkpoint: str | os.PathLike, env_id: str, name: str, *, info: dict | None = None
) -> Path:
    """Turn a training checkpoint (e.g. ``runs/experts/.../ckpt_000700000.pt``) into the zoo policy ``name``.

    The file's own statistics (frames, batch return / cost) are kept in ``info`` with the extra ``info``.

    Examples:
        A checkpoint as :func:`~spoil_torchrl.experts.train_ppo` writes it, exported into a scratch zoo (the
        committed one is ``spoil_torchrl/zoo/``, :data:`ZOO_DIR`):

        >>> import tempfile
        >>> from unittest import mock
        >>> runs = Path(tempfile.mkdtemp())
        >>> actor = make_actor(28, 2, hidden_cells=(8,))
        >>> torch.save({"actor": actor.state_dict(), "frames": 700_000}, runs / "ckpt_000700000.pt")
        >>> with mock.patch(f"{__name__}.ZOO_DIR", runs / "zoo"):
        ...     path = export_checkpoint(runs / "ckpt_000700000.pt", "SafetyPointCircle1-v0", "ppo-0700k")
        >>> path.relative_to(runs).as_posix()
        'zoo/SafetyPointCircle1-v0/ppo-0700k.pt'
        >>> load_policy(path)[1]["info"]
        {'frames': 700000, 'exported_from': 'ckpt_000700000.pt'}
    """
    actor, meta = load_policy(checkpoint, env_id=env_id)
    record = {**meta["info"], **(info or {}), "exported_from": Path(checkpoint).name}
    return save_policy(ZOO_DIR / env_id / f"{name}.pt", actor, env_id=env_id, info=record)


def zoo_names(env_id: str) -> list[str]:
    """Names of the committed policies for ``env_id`` (empty if none).

    Examples:
        >>> [n for n in zoo_names("SafetyPointCircle1-v0") if n.endswith(("-high", "-medium"))]
        ['safe-high', 'safe-medium', 'unsafe-high', 'unsafe-medium']
    """
    folder = ZOO_DIR / env_id
    return sorted(p.stem for p in folder.glob("*.pt")) if folder.is_dir() else []


def zoo_policy(env_id: str, name: str) -> Path:
    """The path of the committed policy ``name`` for ``env_id``; raises with the available names.

    Examples:
        >>> path = zoo_policy("SafetyHopperVelocity-v1", "safe-high")
        >>> path.relative_to(ZOO_DIR).as_posix()
        'SafetyHopperVelocity-v1/safe-high.pt'
        >>> load_policy(path, env_id="SafetyHopperVelocity-v1")[1]["action_dim"]
        3
        >>> zoo_policy("SafetyHopperVelocity-v1", "expert")
        Traceback (most recent call last):
        ...
        spoil_torchrl.zoo.policy_files.PolicyFileError: no committed policy 'expert' for \
SafetyHopperVelocity-v1; available: ...
    """
    path = ZOO_DIR / env_id / f"{name}.pt"
    if not path.is_file():
        available = zoo_names(env_id)
        raise PolicyFileError(
            f"no committed policy {name!r} for {env_id}; "
            + (f"available: {', '.join(available)}" if available else "this task has none")
        )
    return path


def policy_path(spec: str, env_id: str) -> Path:
    """The file a policy spec names: ``zoo:<name>`` (the committed policy ``name`` of ``env_id``, see
    :func:`zoo_policy`) or a path.

    Examples:
        >>> policy_path("zoo:safe-high", "SafetyPointCircle1-v0").name, policy_path("a/b.pt", "any").as_posix()
        ('safe-high.pt', 'a/b.pt')
    """
    return zoo_policy(env_id, spec.removeprefix("zoo:")) if spec.startswith("zoo:") else Path(spec)
