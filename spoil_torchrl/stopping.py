"""Stopping a run on a signal: SIGTERM (``kill``, a scheduler's pre-emption) ends training as Ctrl-C does,
at a boundary the training loop chooses, so that what the run keeps on disk is whole.

The offline trainer and the expert trainer both ask here; neither handles signals itself.
"""

from __future__ import annotations

import signal
from collections.abc import Sequence

_stop_reason: str | None = None


def stop_on_signals(signals: Sequence[int] = (signal.SIGTERM,)) -> None:
    """Make ``signals`` (default SIGTERM: ``kill``, a scheduler's pre-emption) end training cleanly.

    The handler only records the signal; every :func:`~spoil_torchrl.trainers.offline_trainer` raises
    ``KeyboardInterrupt`` at its next chunk boundary (at most ``steps_per_batch`` steps later), from its own
    hook, so the interrupt never lands inside library code and the caller handles it like Ctrl-C; other loops
    (an expert's training) ask :func:`stop_requested` at their own boundaries. A second signal interrupts at
    once.

    Examples:
        >>> previous = signal.getsignal(signal.SIGUSR1)
        >>> stop_on_signals((signal.SIGUSR1,))  # at the start of a run (default: SIGTERM)
        >>> signal.raise_signal(signal.SIGUSR1)  # as `kill -USR1 <pid>` would
        >>> stop_requested()
        'signal SIGUSR1'
        >>> try:
        ...     raise_if_stopped()  # what offline_trainer does after every chunk of steps
        ... except KeyboardInterrupt as stop:
        ...     print("training stopped:", stop)
        training stopped: signal SIGUSR1
        >>> import spoil_torchrl.stopping as stopping  # undo, for the examples that follow:
        >>> stopping._stop_reason = None; _ = signal.signal(signal.SIGUSR1, previous)
    """

    def handler(signum, frame):
        global _stop_reason
        if _stop_reason is not None:
            raise KeyboardInterrupt(_stop_reason)
        _stop_reason = f"signal {signal.Signals(signum).name}"

    for signum in signals:
        signal.signal(signum, handler)


def stop_requested() -> str | None:
    """The signal :func:`stop_on_signals` caught (``"signal SIGTERM"``), or ``None``."""
    return _stop_reason


def raise_if_stopped() -> None:
    """Raise ``KeyboardInterrupt`` if a signal asked the run to stop (see :func:`stop_on_signals`)."""
    if _stop_reason is not None:
        raise KeyboardInterrupt(_stop_reason)
