"""How a recipe's process ends when its run stops early: one line and an exit status, never a traceback for
what the user can fix.

:func:`ended_in_one_line` wraps a recipe's run. The run itself has already recorded why it stopped in its
``results.json`` (``failed`` / ``interrupted``); this turns the exception into what the user reads:

========================================  ==========================================================  ======
what stopped the run                      the line                                                    status
========================================  ==========================================================  ======
a setting, file or run directory          ``error: <what and how to fix it>``                         2
(:data:`USER_ERRORS`)
divergence (:class:`TrainingDiverged`)    ``failed: <step>: <loss> is not finite ...``                1
a full disk, a quota, a read-only place   ``error: cannot write <file>: <reason>; ... marked failed`` 1
Ctrl-C, SIGTERM                           ``interrupted; continue with: <the command>``               130
========================================  ==========================================================  ======

Anything else is a bug and keeps its traceback; ``HYDRA_FULL_ERROR=1`` shows the traceback of every case.
In a job of a sweep (``keep_going``), a diverged run prints its line and the sweep goes on with its next job:
one cell's divergence is a result (the report lists it as failed), not a reason to stop the other cells.
"""

from __future__ import annotations

import contextlib
import errno
import os
import sys
from collections.abc import Iterator
from pathlib import Path

from spoil_torchrl.data.episodes import DatasetError
from spoil_torchrl.divergence import TrainingDiverged
from spoil_torchrl.runs.checkpoint import CheckpointError
from spoil_torchrl.runs.directory import RunDirError
from spoil_torchrl.runs.settings import SettingsError
from spoil_torchrl.tasks import UnknownDatasetError

#: Errors that are the user's to fix (a setting, a file, a run directory).
USER_ERRORS = (SettingsError, RunDirError, CheckpointError, DatasetError, UnknownDatasetError)
#: OS errors of a place that cannot take more writes (a full disk, a quota, a file-size limit, read-only).
DISK_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES)


def resume_command(recipe: str, run_dir: str | os.PathLike) -> str:
    """The command that continues the interrupted run of this Hydra job in ``run_dir`` (its own overrides,
    ``hydra.run.dir`` and ``resume=true``)."""
    from hydra.core.hydra_config import HydraConfig

    kept = [o for o in HydraConfig.get().overrides.task if not o.startswith(("hydra.run.dir=", "resume="))]
    return " ".join(["python", recipe, *kept, f"hydra.run.dir={run_dir}", "resume=true"])


def is_sweep_job() -> bool:
    """Whether this Hydra job is one job of a sweep (``-m``, or an experiment's ``hydra.mode: MULTIRUN``)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


@contextlib.contextmanager
def ended_in_one_line(recipe: str, run_dir: str | os.PathLike, *, keep_going: bool = False) -> Iterator[None]:
    """Run the body; end the process with the line and status of the table above when it stops early
    (``keep_going``: a diverged run's line only, naming ``run_dir``, and the caller goes on).

    Examples:
        >>> try:
        ...     with ended_in_one_line("recipes/spoildice_dsrl.py", "runs/x"):
        ...         raise SettingsError("train.lr = -1: expected a finite number > 0")
        ... except SystemExit as stop:
        ...     print(stop.code)
        2
    """
    if os.environ.get("HYDRA_FULL_ERROR") == "1":
        yield
        return
    try:
        yield
    except USER_ERRORS as err:
        _exit(f"error: {err}", 2)
    except TrainingDiverged as err:  # marked "failed" in results.json; the report leaves it out
        if keep_going:
            print(f"failed: {Path(run_dir)}: {err}", file=sys.stderr)
            return
        _exit(f"failed: {err}", 1)
    except OSError as err:
        if err.errno not in DISK_ERRORS:
            raise
        where = err.filename or f"into {Path(run_dir)}"
        _exit(f"error: cannot write {where}: {err.strerror}; the run is marked failed", 1)
    except KeyboardInterrupt:  # marked "interrupted", its last checkpoint intact
        _exit(f"interrupted; continue with: {resume_command(recipe, run_dir)}", 130)


def _exit(line: str, status: int) -> None:
    print(line, file=sys.stderr)
    raise SystemExit(status)
