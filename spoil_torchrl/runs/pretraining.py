"""A run's pre-training, stored once it is done and loaded by a resumed run instead of computed again.

The pre-training stage of an algorithm (:class:`~spoil_torchrl.algorithms.Pretraining`: the annotations it wrote
into the buffers, its diagnostics and its frozen networks) is written into ``checkpoints/pretraining.pt`` of the
run directory before the main stage starts (:func:`save_pretraining`: atomic and checksummed, like the training
state). A resumed run loads it (:func:`load_pretraining`) and writes the stored annotations into its freshly
loaded buffers, so it spends no time on pre-training, and it continues exactly where a recomputed pre-training
would come out different (another CPU, BLAS path or library build). What it refuses, in one line naming the
file and before anything in the run directory changes: a damaged or truncated file, one made with other settings
(:func:`~spoil_torchrl.runs.resume.settings_differ`), and one made on other data (:func:`check_same_data`: the
fingerprint of the prepared transitions before any annotation).

Runs made before pre-trainings were stored have no such file; they resume as they always did, by computing the
pre-training again and checking that it reproduces the checkpoint's fingerprint.
"""

from __future__ import annotations

from pathlib import Path

from spoil_torchrl.algorithms import Pretraining
from spoil_torchrl.runs.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from spoil_torchrl.runs.resume import pretraining_fingerprint, settings_differ


class StoredPretrainingRefused(CheckpointError):
    """A stored pre-training that does not belong to the run's data, found before the resumed run wrote
    anything: the run directory is left as it was (its lock included, :func:`~spoil_torchrl.runs.claim.claim_runs`)."""


#: Where a run stores its pre-training (relative to the run directory).
PRETRAINING_NAME = "checkpoints/pretraining.pt"
#: Written into every stored pre-training; a file of another kind is refused.
PRETRAINING_FORMAT = "spoil_torchrl.pretraining/1"


def data_fingerprint(buffers) -> str:
    """SHA-256 of every role's stored transitions as they are now (before the pre-training annotates them:
    the data a stored pre-training belongs to)."""
    return pretraining_fingerprint(buffers, {})


def save_pretraining(
    run_dir: str | Path, pretraining: Pretraining, *, config_yaml: str, data: str, algo: str, machine: dict
) -> None:
    """Store ``pretraining`` in ``run_dir`` (:data:`PRETRAINING_NAME`) with the run's settings ``config_yaml``,
    its data fingerprint ``data`` (:func:`data_fingerprint`), the algorithm's name and the ``machine`` it was
    computed on (:func:`~spoil_torchrl.stack.current_machine`).

    Examples:
        >>> import tempfile
        >>> run_dir = Path(tempfile.mkdtemp())
        >>> stage = Pretraining(diagnostics={"support_threshold": 0.25})
        >>> save_pretraining(run_dir, stage, config_yaml="seed: 0", data="abc", algo="fbc", machine={})
        >>> load_pretraining(run_dir, "seed: 0", algo="fbc")[0].diagnostics["support_threshold"]
        0.25
        >>> load_pretraining(run_dir, "seed: 1", algo="fbc")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        spoil_torchrl.runs.checkpoint.CheckpointError: .../checkpoints/pretraining.pt: made with other settings (seed)...
    """
    save_checkpoint(
        Path(run_dir) / PRETRAINING_NAME,
        {
            "format": PRETRAINING_FORMAT,
            "algo": algo,
            "config_yaml": config_yaml,
            "data_fingerprint": data,
            "machine": machine,
            **pretraining.as_state(),
        },
    )


def load_pretraining(run_dir: str | Path, config_yaml: str, *, algo: str) -> tuple[Pretraining, dict]:
    """The pre-training stored in ``run_dir`` for a run with settings ``config_yaml`` of algorithm ``algo``, and
    its record (``data_fingerprint``, ``machine``).

    Raises:
        CheckpointError: the file is unreadable or damaged, of another kind, or made with other settings or by
            another algorithm (one line, naming the file).
    """
    path = Path(run_dir) / PRETRAINING_NAME
    try:
        state = load_checkpoint(path)
    except CheckpointError as err:  # what to do about it, in the same line
        raise CheckpointError(
            f"{err}; delete it to resume by computing the pre-training again (exact on the machine that made "
            "the run)"
        ) from None
    if state.get("format") != PRETRAINING_FORMAT:
        raise CheckpointError(f"{path}: not a stored pre-training (format {state.get('format')!r})")
    if state.get("algo") != algo:
        raise CheckpointError(f"{path}: the pre-training of {state.get('algo')!r}, not of {algo!r}")
    differ = settings_differ(state["config_yaml"], config_yaml)
    if differ:
        raise CheckpointError(
            f"{path}: made with other settings ({', '.join(differ)}) than the run's; resume with the run's own "
            "settings or start a new run"
        )
    stage = Pretraining(state["annotations"], state["diagnostics"], state["networks"])
    return stage, {"data_fingerprint": state["data_fingerprint"], "machine": state["machine"]}


def check_same_data(path: str | Path, record: dict, buffers) -> None:
    """Refuse (:class:`StoredPretrainingRefused`) a stored pre-training whose data fingerprint is not that of ``buffers``
    (the run's data, prepared again: another dataset file, or the same name made differently)."""
    if record["data_fingerprint"] != data_fingerprint(buffers):
        raise StoredPretrainingRefused(
            f"{path}: made on other data than the run's dataset now holds (another file, or one made again "
            "differently); resume with the run's own data file or start a new run"
        )
