"""A run directory's life: one process writes it at a time, and no start ever destroys a run that is there.

:func:`claim_run_dir` is the first thing a run does: it refuses a directory that another live process is
writing, refuses to start over a run that is already there unless asked to resume it, and then writes a lock
file (``run.lock``: the process id, its start time, the host and the cluster job, if any) that
:func:`release_run_dir` removes at the end. A run killed with SIGKILL cannot mark itself, but it leaves its
lock behind with a process id that is gone; :func:`run_status` reads that as ``"killed"``, so a reader
(``recipes/report.py``) can tell a killed run from one that is still training.
"""

from __future__ import annotations

import json
import os
import socket
import time
from pathlib import Path

from spoil_torchrl.files import write_atomic

#: The lock file a running run keeps in its directory.
LOCK_NAME = "run.lock"
#: The training-state checkpoint a run resumes from (relative to the run directory).
CHECKPOINT_NAME = "checkpoints/training_state.pt"
#: The ``resume`` settings: start only in an empty directory / continue a run / continue if possible.
RESUME_CHOICES = (False, True, "auto")


class RunDirError(ValueError):
    """The run directory cannot be used as asked (another process writes it, or it already holds a run)."""


def _process_start(pid: int) -> str | None:
    """The start time of process ``pid`` in clock ticks since boot (Linux), to tell a reused pid apart."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()[19]  # field 22 of proc(5), counted after the command name


def _scheduler_job() -> str | None:
    """The cluster job this process belongs to (SLURM keeps the id when it requeues a job), if any."""
    job = os.environ.get("SLURM_JOB_ID")
    return None if job is None else f"slurm:{job}:{os.environ.get('SLURM_ARRAY_TASK_ID', '')}"


def _alive(lock: dict) -> bool | None:
    """Whether the lock's process still runs (``None``: it ran on another host, so this one cannot tell).
    A lock left by an earlier start of this very cluster job (requeued after pre-emption) is dead."""
    if lock.get("job") is not None and lock.get("job") == _scheduler_job() and lock.get("pid") != os.getpid():
        return False
    if lock.get("host") != socket.gethostname():
        return None
    pid = int(lock.get("pid", -1))
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        pass
    started = lock.get("process_start")
    return started is None or _process_start(pid) in (None, started)


def read_lock(run_dir: str | os.PathLike) -> dict | None:
    """The lock of ``run_dir`` (``None`` if there is none or it cannot be read)."""
    try:
        lock = json.loads((Path(run_dir) / LOCK_NAME).read_text())
    except (OSError, ValueError):
        return None
    return lock if isinstance(lock, dict) else None


def _read_results(run_dir: Path) -> dict | None:
    try:
        results = json.loads((run_dir / "results.json").read_text())
    except (OSError, ValueError):
        return None
    return results if isinstance(results, dict) else None


def run_status(run_dir: str | os.PathLike, results: dict | None = None) -> str:
    """The run's state: its ``results.json`` status (``"finished"``, ``"failed"``, ``"interrupted"``, ...),
    except that a run still marked ``"pre-training"`` / ``"training"`` whose process is gone is ``"killed"``
    (``"running on <host>"`` when it ran on another host); ``"missing"`` without a readable ``results.json``.
    """
    run_dir = Path(run_dir)
    results = _read_results(run_dir) if results is None else results
    if results is None:
        return "missing"
    status = str(results.get("status", "missing"))
    if status not in ("pre-training", "training"):
        return status
    lock = read_lock(run_dir)
    alive = None if lock is None else _alive(lock)
    if lock is None or alive is False:
        return "killed"
    return status if alive else f"{status} on {lock.get('host')}"


def claim_run_dir(run_dir: str | os.PathLike, *, resume: bool | str = False) -> bool:
    """Take ``run_dir`` for this process; returns whether the run there is to be resumed.

    Args:
        run_dir: the run directory (it may already exist, e.g. with Hydra's ``.hydra`` folder).
        resume: ``False`` -- start a new run; a directory that already holds one (a ``results.json``) is
            refused. ``True`` -- continue the run there from its checkpoint (refused without one).
            ``"auto"`` -- continue if there is a checkpoint, else start afresh (what a requeued cluster job
            wants).

    Raises:
        RunDirError: another live process writes the directory, it holds a run and ``resume`` is ``False``,
            or ``resume=True`` finds nothing to continue.

    Examples:
        >>> import tempfile
        >>> run_dir = Path(tempfile.mkdtemp())
        >>> claim_run_dir(run_dir)  # a new run
        False
        >>> _ = (run_dir / "results.json").write_text('{"status": "training"}')
        >>> run_status(run_dir)  # this process holds the lock
        'training'
        >>> release_run_dir(run_dir)
        >>> run_status(run_dir)  # the lock is gone and the run never finished: killed
        'killed'
        >>> claim_run_dir(run_dir)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        spoil_torchrl.trainers.run_dir.RunDirError: ... already holds a run (status killed)...
    """
    if resume not in RESUME_CHOICES:
        raise RunDirError(f"resume must be one of true, false, auto; got {resume!r}")
    run_dir = Path(run_dir)
    lock = read_lock(run_dir)
    if lock is not None and lock.get("pid") != os.getpid() and _alive(lock) is not False:
        where = f"process {lock.get('pid')} on {lock.get('host')}"
        raise RunDirError(
            f"{run_dir} is being written by {where} (its {LOCK_NAME}); wait for it or stop it. If that "
            f"process is gone (e.g. another machine was switched off), delete {run_dir / LOCK_NAME}."
        )
    results = _read_results(run_dir)
    checkpoint = (run_dir / CHECKPOINT_NAME).is_file()
    status = run_status(run_dir, results) if results is not None else None
    if resume is False and (results is not None or (run_dir / "results.json").exists()):
        raise RunDirError(
            f"{run_dir} already holds a run (status {status}). Continue it with resume=true (and the same "
            "hydra.run.dir), or start a fresh run in a new directory: leave hydra.run.dir at its default "
            "(a new time-stamped folder) or delete this one."
        )
    if resume and status == "finished":  # true or auto
        raise RunDirError(f"{run_dir}: the run there has finished; there is nothing to resume")
    if resume is True and not checkpoint:
        raise RunDirError(
            f"resume=true, but {run_dir} has no checkpoint ({CHECKPOINT_NAME}: it is written at every "
            "evaluation with train.checkpoint=true); start afresh with resume=auto or in a new directory"
        )
    run_dir.mkdir(parents=True, exist_ok=True)
    write_lock(run_dir)
    return bool(resume) and checkpoint


def write_lock(run_dir: str | os.PathLike) -> None:
    """Write (or refresh, as a heartbeat) this process's lock in ``run_dir``."""
    lock = {
        "pid": os.getpid(),
        "process_start": _process_start(os.getpid()),
        "host": socket.gethostname(),
        "job": _scheduler_job(),
        "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    write_atomic(Path(run_dir) / LOCK_NAME, json.dumps(lock))


def release_run_dir(run_dir: str | os.PathLike) -> None:
    """Remove this process's lock (another process's lock is left alone)."""
    lock = read_lock(run_dir)
    if lock is not None and lock.get("pid") == os.getpid() and lock.get("host") == socket.gethostname():
        (Path(run_dir) / LOCK_NAME).unlink(missing_ok=True)
