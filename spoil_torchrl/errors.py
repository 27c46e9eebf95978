"""The error a setting with a value it cannot have raises, wherever it is found (the run's settings check, an
algorithm's builder, the expert trainer): one type, so that every recipe reports it in one line."""

from __future__ import annotations


class SettingsError(ValueError):
    """A setting with a value it cannot have."""
