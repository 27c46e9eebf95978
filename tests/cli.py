"""Commands run inside the test process, as a shell would run them, without a Python start per test.

A recipe started with ``subprocess`` pays the interpreter and the torch / TorchRL / Hydra imports (3-8 s) before
its first line; most tests only care about what the command then does. :func:`run_command` calls the same entry
point the console script calls (``spoil_torchrl.recipes.<name>:main``, ``spoil_torchrl.inspect:main``) with
``sys.argv`` set, so Hydra composes, validates, names the run directory and writes ``.hydra/`` as it does on the
command line, and returns what a finished process would: exit status, stdout, stderr. What the command changes
in the process (logging handlers, signal handlers, torch's thread count, warnings filters, the working
directory, the environment, Hydra's singletons) is put back afterwards.

``real=True`` runs the same command in a new Python process instead. One test per console script does so, so
that what only a process shows (its imports, its exit status, what it prints before the first line of ours)
stays covered: the kill-and-resume tests (``spoil-train``; ``spoil-report`` beside the first), and one test
each of the other recipes and of ``spoil-inspect`` (look for ``real=True``).

    ran = run_command(["recipes/report.py", "/no/such/folder"])
    assert ran.returncode == 1 and "no such folder" in ran.stderr
"""

from __future__ import annotations

import contextlib
import importlib
import io
import logging
import os
import signal
import subprocess
import sys
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class Ran:
    """What a command left behind, like :class:`subprocess.CompletedProcess`."""

    returncode: int
    stdout: str
    stderr: str


def _entry_point(argv: list[str]) -> tuple[str, callable, list[str]]:
    """``[recipes/<name>.py, *args]`` or ``["-m", module, *args]`` -> (program name, main, args)."""
    if argv[0] == "-m":
        return argv[1], importlib.import_module(argv[1]).main, argv[2:]
    path = Path(argv[0])
    if path.parent.name != "recipes" or path.suffix != ".py":
        raise ValueError(f"not a recipe or a module: {argv[0]}")
    return str(path), importlib.import_module(f"spoil_torchrl.recipes.{path.stem}").main, argv[1:]


def _logging_state() -> dict:
    loggers = [logging.getLogger()] + [
        logger for logger in logging.Logger.manager.loggerDict.values() if isinstance(logger, logging.Logger)
    ]
    return {
        logger: (logger.level, list(logger.handlers), logger.propagate, logger.disabled) for logger in loggers
    }


def _restore_logging(state: dict) -> None:
    """Put back the loggers that existed before the command (a logger made during it, e.g. by a library's
    first import, stays as its library set it up). Of the handlers the command attached, only a plain
    ``logging.FileHandler`` (a run's log file, as Hydra opens it) is closed: another handler may hold a stream
    it does not own, such as this process's stderr, which closing would close for every later test."""
    for logger, (level, handlers, propagate, disabled) in state.items():
        for handler in logger.handlers:
            if handler not in handlers and type(handler) is logging.FileHandler:
                handler.close()
        logger.handlers[:] = handlers
        logger.setLevel(level)
        logger.propagate, logger.disabled = propagate, disabled


class _Capture(io.StringIO):
    """What the command prints; a handler that closes its stream (below) cannot close it."""

    def close(self) -> None:
        pass


def _shield_streams(out: io.StringIO, err: io.StringIO) -> list:
    """Point every logging handler that holds this process's stdout or stderr at the captures for the command.

    Hydra configures logging with ``dictConfig``, which closes every handler of the process. Some handlers
    close their stream then, unless it is ``sys.stdout`` / ``sys.stderr`` at that moment (absl's, made when
    tensorboard is imported, holds the stderr it found at import): with the command's output captured, that
    stream would be pytest's capture of stderr, closed for every later test."""
    process = {id(sys.stdout): out, id(sys.__stdout__): out, id(sys.stderr): err, id(sys.__stderr__): err}
    swapped = []
    for ref in list(logging._handlerList):
        handler = ref()
        stream = getattr(handler, "stream", None)
        if stream is not None and id(stream) in process:
            try:
                handler.stream = process[id(stream)]
            except AttributeError:  # a read-only view of another handler's stream (absl's), swapped there
                continue
            swapped.append((handler, stream))
    return swapped


def _clear_hydra() -> None:
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.hydra_config import HydraConfig

    GlobalHydra.instance().clear()
    HydraConfig.instance().cfg = None


def run_command(
    argv: list[str], *, cwd: str | os.PathLike | None = None, env: dict | None = None, real: bool = False
) -> Ran:
    """Run ``argv`` (what follows ``python`` on a command line; a recipe's path is relative to the checkout) in
    this process, or in a new one with ``real=True``; see the module's docstring.

    ``env`` replaces the environment for the command, as ``subprocess.run(env=...)`` does. An exception the
    command lets out becomes status 1 with its traceback on stderr, as the interpreter would print it.
    """
    if real:
        argv = [str(ROOT / a) if i == 0 and str(a).endswith(".py") else str(a) for i, a in enumerate(argv)]
        proc = subprocess.run(
            [sys.executable, *argv], capture_output=True, text=True, timeout=600, cwd=cwd or ROOT, env=env
        )
        return Ran(proc.returncode, proc.stdout, proc.stderr)
    program, main, args = _entry_point([str(a) for a in argv])
    out, err = _Capture(), _Capture()
    saved_argv, saved_cwd, saved_env = sys.argv, os.getcwd(), dict(os.environ)
    saved_signals = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    saved_threads, saved_logging = torch.get_num_threads(), _logging_state()
    code = 0
    _clear_hydra()
    swapped = _shield_streams(out, err)
    try:
        sys.argv = [program, *args]
        if env is not None:
            os.environ.clear()
            os.environ.update(env)
        if cwd is not None:
            os.chdir(cwd)
        with warnings.catch_warnings(), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                returned = main()
                code = returned if isinstance(returned, int) and not isinstance(returned, bool) else 0
            except SystemExit as stop:
                if stop.code is None or isinstance(stop.code, int):
                    code = stop.code or 0
                else:  # sys.exit("message"): the message on stderr, status 1
                    print(stop.code, file=sys.stderr)
                    code = 1
            except Exception:
                traceback.print_exc()
                code = 1
            finally:
                logging.captureWarnings(False)
    finally:
        sys.argv = saved_argv
        os.chdir(saved_cwd)
        if env is not None:
            os.environ.clear()
            os.environ.update(saved_env)
        for signum, handler in saved_signals.items():
            signal.signal(signum, handler)
        torch.set_num_threads(saved_threads)
        _restore_logging(saved_logging)
        for handler, stream in swapped:
            handler.stream = stream
        _clear_hydra()
    return Ran(code, out.getvalue(), err.getvalue())
