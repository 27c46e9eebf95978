"""What a resumed run checks before it continues, and the logs it puts back to the checkpoint's step.

A run resumes from the checkpoint of its last evaluation (:mod:`spoil_torchrl.runs.checkpoint`). The
pre-training (discriminators, support cut, annotated buffers) is not stored: it is deterministic for a seed
on one machine, so the resumed run does it again and compares :func:`pretraining_fingerprint` with the one in
the checkpoint; the main stage's networks, optimisers, step counters and random-number streams come from
the checkpoint. :func:`settings_differ` refuses a resume with other settings, and :func:`trim_csv_logs` cuts
the CSV logs (TorchRL's :class:`~torchrl.record.loggers.CSVLogger`) back to the rows they had at the
checkpoint, so a resumed run's logs hold every step once. :func:`finished_already` lets ``resume=auto`` pass
over a run that has finished with the same settings (a sweep started again skips its finished cells).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from pathlib import Path

from omegaconf import OmegaConf

from spoil_torchrl.devices import DEFAULT_DEVICE
from spoil_torchrl.files import update_digest, write_atomic
from spoil_torchrl.runs.checkpoint import CheckpointError
from spoil_torchrl.runs.directory import RunDirError, run_status
from spoil_torchrl.stack import current_stack, stack_differences, stack_label

#: Settings that may change between a run and its resumption (they do not change what is trained).
RESUMABLE_CHANGES = ("progress",)
#: Settings some runs record and others do not, with the value a run without one had (the versions that wrote
#: ``algo.support: estimated`` into every FBC run's settings, before it became an added key).
IMPLIED_SETTINGS = {
    "algo.support": "estimated",
    "train.penalty_form": "autograd",
    "dataset.constraints": None,
    "dataset.n_safe_per_constraint": None,
    "dataset.constraint_thresholds": None,
    "dataset.constraint_pools": None,
    "eval.constraints": None,
    "device": DEFAULT_DEVICE,
}


def pretraining_fingerprint(buffers, diagnostics: Mapping[str, float]) -> str:
    """SHA-256 of every role's stored transitions (annotations included) and the pre-training diagnostics.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from spoil_torchrl.data import DualDemoBuffers
        >>> episodes = TensorDict({"observation": torch.zeros(2, 1), "episode": torch.tensor([0, 1]),
        ...                        "is_init": torch.ones(2, 1, dtype=torch.bool)}, [2])
        >>> buffers = DualDemoBuffers(episodes, {"unlabeled": [0, 1]}, batch_size=1)
        >>> before = pretraining_fingerprint(buffers, {"threshold": 0.5})
        >>> buffers.annotate("unlabeled", "score", lambda td: td["observation"] + 1)
        >>> before == pretraining_fingerprint(buffers, {"threshold": 0.5})
        False
    """
    digest = hashlib.sha256()
    for role in buffers.roles:
        stored = buffers[role].storage[:]
        for key in sorted(stored.keys(include_nested=True, leaves_only=True), key=str):
            update_digest(digest, f"{role}/{key}", stored.get(key))
    digest.update(json.dumps(dict(diagnostics), sort_keys=True).encode())
    return digest.hexdigest()


def settings_differ(
    old_yaml: str, new_yaml: str, *, allowed: tuple[str, ...] = RESUMABLE_CHANGES
) -> list[str]:
    """The dotted names of the settings that differ between two ``config.yaml`` texts (``allowed`` ignored).

    Examples:
        >>> old = "seed: 0\\ntrain:\\n  lr: 0.1\\nprogress: true"
        >>> settings_differ(old, "seed: 0\\ntrain:\\n  lr: 0.2\\nprogress: false")
        ['train.lr']
        >>> settings_differ("algo:\\n  kappa: 0.01", "algo:\\n  kappa: 0.01\\n  support: estimated")  # implied
        []
    """

    def flat(tree, prefix=""):
        if isinstance(tree, dict):
            out = {}
            for key, value in tree.items():
                out.update(flat(value, f"{prefix}{key}."))
            return out
        return {prefix[:-1]: tree}

    def load(text: str) -> dict:
        return OmegaConf.to_container(OmegaConf.create(text)) if text.strip() else {}

    old, new = flat(load(old_yaml)), flat(load(new_yaml))
    keys = sorted(set(old) | set(new))
    value = lambda settings, k: settings.get(k, IMPLIED_SETTINGS.get(k))  # noqa: E731
    return [k for k in keys if value(old, k) != value(new, k) and k.split(".")[0] not in allowed]


def check_resumable(
    state: Mapping, config_yaml: str, run_dir: str | os.PathLike, *, settings_file: str = "config.yaml"
) -> None:
    """Refuse (``CheckpointError``) to resume from a checkpoint ``state`` with other settings than
    ``config_yaml`` (:func:`settings_differ`) or on another software stack than the run's (its
    ``results.json``'s ``stack``, :mod:`spoil_torchrl.stack`: the simulator's physics differ). A run made before
    runs recorded their stack is not checked for it.

    Examples:
        >>> state = {"config_yaml": "seed: 0", "results": {"stack": dict(current_stack(), mujoco="0.1")}}
        >>> check_resumable(state, "seed: 0", "run")
        Traceback (most recent call last):
        ...
        spoil_torchrl.runs.checkpoint.CheckpointError: run: made on another software stack ...
    """
    differ = settings_differ(state["config_yaml"], config_yaml)
    if differ:
        raise CheckpointError(
            f"{run_dir}: resume=true with other settings than the run's ({', '.join(differ)}); resume "
            f"with the run's own settings (its {settings_file}) or start a new run"
        )
    recorded = state.get("results", {}).get("stack")
    differences = [] if recorded is None else stack_differences(recorded)
    if differences:
        raise CheckpointError(
            f"{run_dir}: made on another software stack ({stack_label(recorded)}; here "
            f"{stack_label(current_stack())}: {', '.join(differences)}), whose simulator "
            "evaluates differently; resume it on its own stack (make STACK=legacy for the legacy one) or start "
            "a new run"
        )


def csv_row_counts(log_dir: str | os.PathLike) -> dict[str, int]:
    """Lines of every ``.csv`` file under ``log_dir`` (relative path -> count; empty without logs)."""
    log_dir = Path(log_dir)
    if not log_dir.is_dir():
        return {}
    counts = {}
    for path in sorted(log_dir.rglob("*.csv")):
        with open(path, "rb") as f:
            counts[str(path.relative_to(log_dir))] = sum(1 for _ in f)
    return counts


def trim_csv_logs(log_dir: str | os.PathLike, counts: Mapping[str, int]) -> None:
    """Cut every ``.csv`` file under ``log_dir`` back to its line count in ``counts`` (files that did not
    exist then are removed), undoing what a killed run logged after its checkpoint.

    Examples:
        >>> import tempfile
        >>> log_dir = Path(tempfile.mkdtemp())
        >>> _ = (log_dir / "loss.csv").write_text("100,0.5\\n")
        >>> counts = csv_row_counts(log_dir)
        >>> _ = (log_dir / "loss.csv").write_text("100,0.5\\n200,0.4\\n"); _ = (log_dir / "new.csv").write_text("1,1\\n")
        >>> trim_csv_logs(log_dir, counts)
        >>> (log_dir / "loss.csv").read_text(), (log_dir / "new.csv").exists()
        ('100,0.5\\n', False)
    """
    log_dir = Path(log_dir)
    for name, rows in csv_row_counts(log_dir).items():
        path = log_dir / name
        keep = counts.get(name, 0)
        if keep == 0:
            path.unlink()
        elif rows > keep:
            with open(path, "rb") as f:
                lines = f.readlines()[:keep]
            write_atomic(path, b"".join(lines))


def finished_already(run_dir: str | os.PathLike, config_yaml: str, resume: bool | str) -> dict | None:
    """The results of the run in ``run_dir`` when ``resume`` is ``"auto"`` and that run has finished with the
    settings ``config_yaml`` (its ``config.yaml``; :data:`RESUMABLE_CHANGES` aside): there is nothing to do, and
    a sweep started again passes over its finished cells. ``None`` otherwise (the run is started or resumed as
    :func:`~spoil_torchrl.runs.directory.claim_run_dir` decides). Nothing is written.

    Raises:
        RunDirError: the finished run was made with other settings (a changed sweep that names its cells
            as before would otherwise pass over runs that are not its own), or on another software stack.

    Examples:
        >>> import tempfile
        >>> run = Path(tempfile.mkdtemp())
        >>> _ = (run / "results.json").write_text('{"status": "finished", "seed": 0}')
        >>> _ = (run / "config.yaml").write_text("seed: 0")
        >>> finished_already(run, "seed: 0", "auto")
        {'status': 'finished', 'seed': 0}
        >>> finished_already(run, "seed: 0", True) is None  # resume=true on a finished run is refused later
        True
        >>> finished_already(run, "seed: 1", "auto")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        spoil_torchrl.runs.directory.RunDirError: ...: the run there has finished, with other settings (seed)...
    """
    run_dir = Path(run_dir)
    if resume != "auto" or run_status(run_dir) != "finished":
        return None
    config = run_dir / "config.yaml"
    differ = settings_differ(config.read_text(), config_yaml) if config.is_file() else []
    if differ:
        raise RunDirError(
            f"{run_dir}: the run there has finished, with other settings ({', '.join(differ)}); start the new "
            "settings in another directory (another hydra.run.dir or hydra.sweep.dir)"
        )
    results = json.loads((run_dir / "results.json").read_text())
    recorded = results.get("stack")
    if recorded is not None and stack_differences(recorded):  # a sweep continued on another simulator
        raise RunDirError(
            f"{run_dir}: the run there has finished on another software stack ({stack_label(recorded)}; here "
            f"{stack_label(current_stack())}); continue the sweep on its own stack or in another hydra.sweep.dir"
        )
    return results
