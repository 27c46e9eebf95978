"""Training-state checkpoints that a run resumes from bit-exactly: atomic, checksummed, ``weights_only``.

A checkpoint is one ``torch.save`` file holding ``{"format", "sha256", "payload"}``: ``payload`` is the
serialised training state (itself a ``torch.save`` byte string) and ``sha256`` its digest, so a file damaged
on disk is refused with :class:`CheckpointError` instead of loading wrong weights. Both levels load with
``weights_only=True`` (no arbitrary code runs when a checkpoint is opened). Files are written through a
temporary file and :func:`os.replace`, so a run killed while saving leaves the previous checkpoint intact.

:func:`rng_state` / :func:`set_rng_state` capture every random-number stream a training step reads: torch's
global generator and each replay buffer's sampling generator (:meth:`DualDemoBuffers.rng_state
<spoil_torchrl.data.DualDemoBuffers.rng_state>`). Evaluations are seeded by themselves and need no state.
"""

from __future__ import annotations

import hashlib
import io
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from spoil_torchrl.files import save_atomic

#: Written into every checkpoint; a file with another format is refused.
CHECKPOINT_FORMAT = "spoil_torchrl.training_state/1"


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: unreadable, of another format, or damaged (checksum mismatch)."""


def save_checkpoint(path: str | os.PathLike, state: Mapping[str, Any]) -> None:
    """Write ``state`` (tensors, numbers, strings, lists and dicts of them) with its SHA-256, atomically.

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "state.pt"
        >>> save_checkpoint(path, {"step": 3, "weights": torch.ones(2)})
        >>> load_checkpoint(path)["step"]
        3
        >>> outer = torch.load(path, weights_only=True)  # damage the state, keep the old checksum
        >>> outer["payload"] = outer["payload"].replace(b"weights", b"weighte")
        >>> torch.save(outer, path)
        >>> load_checkpoint(path)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        spoil_torchrl.runs.checkpoint.CheckpointError: ...
    """
    buffer = io.BytesIO()
    torch.save(dict(state), buffer)
    payload = buffer.getvalue()
    digest = hashlib.sha256(payload).hexdigest()
    save_atomic({"format": CHECKPOINT_FORMAT, "sha256": digest, "payload": payload}, path)


def load_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """The state written by :func:`save_checkpoint`; :class:`CheckpointError` if the file cannot be trusted."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint there")
    try:
        outer = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # a truncated or overwritten file fails inside the unpickler or zip reader
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(err).__name__}: {err})") from None
    if not isinstance(outer, dict) or outer.get("format") != CHECKPOINT_FORMAT:
        found = outer.get("format") if isinstance(outer, dict) else type(outer).__name__
        raise CheckpointError(f"{path}: checkpoint format {found!r}, expected {CHECKPOINT_FORMAT!r}")
    payload = outer.get("payload")
    if not isinstance(payload, bytes) or hashlib.sha256(payload).hexdigest() != outer.get("sha256"):
        raise CheckpointError(f"{path}: the checksum does not match the content (the file is damaged)")
    try:
        return torch.load(io.BytesIO(payload), map_location="cpu", weights_only=True)
    except Exception as err:
        raise CheckpointError(
            f"{path}: the training state cannot be read ({type(err).__name__}: {err})"
        ) from None


def rng_state(buffers=None) -> dict[str, Any]:
    """Torch's global generator state and, when given, every buffer's sampling-generator state (and, for buffers
    on a GPU, that GPU's global generator: the penalty's draws of a ``device=cuda`` run)."""
    state: dict[str, Any] = {"torch": torch.get_rng_state()}
    if buffers is not None:
        state["buffers"] = buffers.rng_state()
        if buffers.device.type == "cuda":
            state["cuda"] = torch.cuda.get_rng_state(buffers.device)
    return state


def set_rng_state(state: Mapping[str, Any], buffers=None) -> None:
    """Restore what :func:`rng_state` returned."""
    torch.set_rng_state(state["torch"])
    if buffers is not None:
        buffers.set_rng_state(state["buffers"])
        if "cuda" in state:
            torch.cuda.set_rng_state(state["cuda"], buffers.device)
