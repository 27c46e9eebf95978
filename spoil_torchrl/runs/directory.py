"""A run directory's life: one process writes it at a time, and no start ever destroys a run that is there.

:func:`claim_run_dir` is the first thing a run does, before anything is written into the directory: it takes
an exclusive :func:`fcntl.flock` on the lock file (``run.lock``), so of many processes started at once on one
directory exactly one goes on; it refuses a directory that another live process is writing, refuses to start
over a run that is already there unless asked to resume it, and then writes into the lock file the process id,
its start time, the host and the cluster job, if any. The operating system drops the ``flock`` when the process
ends, however it ends; :func:`release_run_dir` removes the file at the end. A refused start writes nothing.

A run killed with SIGKILL cannot mark itself, but it leaves its
lock behind with a process id that is gone; :func:`run_status` reads that as ``"killed"``, so a reader
(``recipes/report.py``) can tell a killed run from one that is still training.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import sys
import time
from collections.abc import Callable
from pathlib import Path

from hydra.experimental.callback import Callback

from spoil_torchrl.files import write_atomic

#: The lock file a running run keeps in its directory.
LOCK_NAME = "run.lock"
#: Its content, a JSON record padded with spaces to this size (rewritten in place as a heartbeat).
LOCK_RECORD_BYTES = 1024
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


def _flocked(run_dir: Path) -> bool:
    """Whether some process holds the flock of ``run_dir``'s lock file (this host, or a file system that
    shares flocks)."""
    try:
        fd = os.open(Path(run_dir) / LOCK_NAME, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)
    return False


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


def run_status(run_dir: str | os.PathLike, results: dict | None = None, *, _probe_flock: bool = True) -> str:
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
    if lock is None and _probe_flock and _flocked(run_dir):  # a claim in progress: its owner is alive
        return status
    alive = None if lock is None else _alive(lock)
    if lock is None or alive is False:
        return "killed"
    return status if alive else f"{status} on {lock.get('host')}"


def claim_run_dir(
    run_dir: str | os.PathLike,
    *,
    resume: bool | str = False,
    check: Callable[[bool], None] | None = None,
) -> bool:
    """Take ``run_dir`` for this process; returns whether the run there is to be resumed.

    Args:
        run_dir: the run directory (it may already exist, e.g. with Hydra's ``.hydra`` folder).
        resume: ``False`` -- start a new run; a directory that already holds one (a ``results.json``) is
            refused. ``True`` -- continue the run there from its checkpoint (refused without one).
            ``"auto"`` -- continue if there is a checkpoint, else start afresh (what a requeued cluster job
            wants).
        check: called with whether the run is to be resumed, after these checks and before anything is written
            (e.g. that a resumed run's settings are its own): what it raises refuses the claim, and the
            directory is left as it was.

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
        spoil_torchrl.runs.directory.RunDirError: ... already holds a run (status killed)...
    """
    if resume not in RESUME_CHOICES:
        raise RunDirError(f"resume must be one of true, false, auto; got {resume!r}")
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise RunDirError(f"{run_dir} is a file, not a run directory; choose another hydra.run.dir")
    held = str(run_dir.resolve()) in _HELD
    fd, created = (None, False) if held else _flock(run_dir)
    try:
        resuming = _check_claim(run_dir, resume)
        if check is not None:
            check(resuming)
        write_lock(run_dir, fd)
    except BaseException:
        if created:  # a refused start leaves the directory as it found it
            (run_dir / LOCK_NAME).unlink(missing_ok=True)
        if fd is not None:
            os.close(fd)
        raise
    if fd is not None:
        _HELD[str(run_dir.resolve())] = fd
    return resuming


#: The lock files this process holds (resolved run directory -> open descriptor with the flock).
_HELD: dict[str, int] = {}


def _flock(run_dir: Path) -> tuple[int, bool]:
    """Open ``run.lock`` and take its exclusive flock without waiting; refuse if another process has it.
    Returns the descriptor and whether this call created the file."""
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise RunDirError(f"{run_dir}: cannot create the run directory ({err.strerror})") from None
    path = run_dir / LOCK_NAME
    while True:
        try:
            try:
                fd, created = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644), True
            except FileExistsError:
                fd, created = os.open(path, os.O_RDWR), False
        except FileNotFoundError:  # removed between the two opens: try again
            continue
        except OSError as err:
            raise RunDirError(
                f"{run_dir}: cannot write there ({err.strerror}); choose another hydra.run.dir"
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            lock = read_lock(run_dir) or {}
            where = f"process {lock.get('pid', '?')} on {lock.get('host', '?')}"
            raise RunDirError(
                f"{run_dir} is being written by {where} (it holds {LOCK_NAME}); wait for it or stop it"
            ) from None
        try:  # the file may have been released (removed) between the open and the flock: then try again
            if os.fstat(fd).st_ino == os.stat(path).st_ino:
                return fd, created
        except FileNotFoundError:
            pass
        os.close(fd)


def _check_claim(run_dir: Path, resume: bool | str) -> bool:
    """Whether the claimed ``run_dir`` is to be resumed (:func:`claim_run_dir`'s checks, under the flock)."""
    lock = read_lock(run_dir)
    if lock is not None and lock.get("pid") != os.getpid() and _alive(lock) is not False:
        where = f"process {lock.get('pid')} on {lock.get('host')}"
        raise RunDirError(
            f"{run_dir} is being written by {where} (its {LOCK_NAME}); wait for it or stop it. If that "
            f"process is gone (e.g. another machine was switched off), delete {run_dir / LOCK_NAME}."
        )
    results = _read_results(run_dir)
    checkpoint = (run_dir / CHECKPOINT_NAME).is_file()
    # (this process holds the flock now: the lock's content alone says whether its last owner lives)
    status = run_status(run_dir, results, _probe_flock=False) if results is not None else None
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
            "evaluation with train.checkpoint=true, and every ppo.checkpoint_every batches of an expert's training); "
            "start afresh with resume=auto or in a new directory"
        )
    return bool(resume) and checkpoint


def write_lock(run_dir: str | os.PathLike, fd: int | None = None) -> None:
    """Write (or refresh, as a heartbeat) this process's lock in ``run_dir``, in place (the file keeps its
    flock; ``fd``: its descriptor, else the one this process holds)."""
    lock = {
        "pid": os.getpid(),
        "process_start": _process_start(os.getpid()),
        "host": socket.gethostname(),
        "job": _scheduler_job(),
        "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    if fd is None:
        fd = _HELD.get(str(Path(run_dir).resolve()))
    if fd is None:  # not claimed by this process (a caller refreshing a lock it does not hold)
        write_atomic(Path(run_dir) / LOCK_NAME, json.dumps(lock))
        return
    # one write of a fixed size, never a truncation: a reader sees the old record or the new one
    data = json.dumps(lock).encode().ljust(LOCK_RECORD_BYTES)
    os.pwrite(fd, data, 0)


def release_run_dir(run_dir: str | os.PathLike) -> None:
    """Remove this process's lock and drop its flock (another process's lock is left alone)."""
    fd = _HELD.pop(str(Path(run_dir).resolve()), None)
    lock = read_lock(run_dir)
    if lock is not None and lock.get("pid") == os.getpid() and lock.get("host") == socket.gethostname():
        (Path(run_dir) / LOCK_NAME).unlink(missing_ok=True)
    if fd is not None:
        os.close(fd)


def write_hydra_record(run_dir: str | os.PathLike, cfg) -> None:
    """Hydra's record of the command (``.hydra/config.yaml``, ``hydra.yaml``, ``overrides.yaml``), written by the
    recipe once it has claimed ``run_dir`` (its configs set ``hydra.output_subdir: null``, so Hydra itself
    writes nothing into a directory before the claim: a refused command leaves a run's record as it was).
    Outside a Hydra job (settings composed with ``hydra.compose`` by a script of one's own) the record is the
    settings alone."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf

    folder = Path(run_dir) / ".hydra"
    write_atomic(folder / "config.yaml", OmegaConf.to_yaml(cfg))
    if not HydraConfig.initialized():
        return
    hydra_cfg = HydraConfig.get()
    write_atomic(folder / "hydra.yaml", OmegaConf.to_yaml(OmegaConf.create({"hydra": hydra_cfg})))
    write_atomic(folder / "overrides.yaml", OmegaConf.to_yaml(list(hydra_cfg.overrides.task)))


def unusable_run_dir(run_dir: str | os.PathLike) -> str | None:
    """Why ``run_dir`` cannot be a run directory (a file is there, it cannot be created, or it is not
    writable), or ``None``; a missing directory is created (as Hydra would), an existing one is left as it is.

    Examples:
        >>> unusable_run_dir("/proc/no-such-run")
        '/proc/no-such-run cannot be created (No such file or directory); choose another hydra.run.dir'
    """
    path = Path(run_dir).absolute()
    if path.exists() and not path.is_dir():
        return f"{path} is a file, not a run directory; choose another hydra.run.dir"
    if not path.exists():
        try:
            path.mkdir(parents=True)
        except FileExistsError:  # made meanwhile, or a file on the way
            if not path.is_dir():
                return f"{path} cannot be created: a file is on its path; choose another hydra.run.dir"
        except OSError as err:
            return f"{path} cannot be created ({err.strerror}); choose another hydra.run.dir"
    elif not os.access(path, os.W_OK | os.X_OK):
        return f"{path} is not writable; choose another hydra.run.dir"
    return None


class RunDirCheck(Callback):
    """A Hydra callback (``hydra.callbacks``) that refuses an unusable ``hydra.run.dir`` in one line before
    Hydra creates it (Hydra's own ``mkdir`` would end in a traceback)."""

    def on_run_start(self, config, **kwargs) -> None:
        problem = unusable_run_dir(config.hydra.run.dir)
        if problem is not None:
            print(f"error: {problem}", file=sys.stderr)
            raise SystemExit(2)
