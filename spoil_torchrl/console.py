"""What a process of this library prints: third-party notices that concern none of our tasks are dropped.

(The recipes' own lines and TorchRL's logger go through Python logging as configured by
``configs/hydra/job_logging/spoil.yaml``: plain lines on the console, the same lines with time and source in
the run's ``.log`` file, TorchRL's INFO chatter and its ANSI colour codes left out.)

Importing gymnasium loads its environment plugins, among them gymnasium-robotics (a dependency of
safety-gymnasium), whose 1.2.x releases print to stderr, twice, through the table of the
``farama_notifications`` package, that the reward of the Adroit-hand tasks changed in 1.2.1 without a version
change. No task of ours is an Adroit task, so every process of ours would print a warning that cannot concern
its user. :func:`quiet_unrelated_notices` (run when :mod:`spoil_torchrl` is imported, before anything imports
gymnasium) removes just the entries that name those tasks; any other notice of that table still prints.

Example:
    >>> from farama_notifications import notifications
    >>> quiet_unrelated_notices()
    >>> [text for versions in notifications.values() for text in versions.values() if "AdroitHand" in text]
    []
"""

from __future__ import annotations

__all__ = ["UNRELATED_NOTICES", "quiet_unrelated_notices"]

#: words that mark a ``farama_notifications`` entry as concerning no task of this library
UNRELATED_NOTICES = ("AdroitHand",)


def quiet_unrelated_notices() -> None:
    """Drop the ``farama_notifications`` entries that name only tasks this library never uses."""
    try:
        from farama_notifications import notifications
    except ImportError:  # not installed: nothing will print
        return
    for versions in notifications.values():
        for version, text in list(versions.items()):
            if any(marker in str(text) for marker in UNRELATED_NOTICES):
                del versions[version]
