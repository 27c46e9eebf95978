"""Settings rules: what a value must be, said once for every recipe.

A rule is a pair ``(check, expected)``: a predicate of the value, and what is expected in words, which ends up in
a :class:`~spoil_torchrl.errors.SettingsError` naming the dotted key and the value (``train.lr = -1: expected a
finite number > 0``). The main recipe's tables are in :mod:`spoil_torchrl.runs.settings`, the tabular recipes'
in :mod:`spoil_torchrl.tabular.settings`; both are built from the predicates here and walked by
:func:`check_keys` / :func:`check_section`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

from spoil_torchrl.errors import SettingsError

#: A setting's check and what it expects.
Rule = tuple[Callable[[Any], bool], str]


def number(value: Any) -> bool:
    """A finite int or float (not a bool).

    Examples:
        >>> number(1), number(2.5), number(True), number(float("inf")), number("1")
        (True, True, False, False, False)
    """
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def positive_int(value: Any) -> bool:
    """An integer >= 1."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= 1


def seed(value: Any) -> bool:
    """An integer >= 0."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def open_unit(value: Any) -> bool:
    """A number in (0, 1)."""
    return number(value) and 0.0 < value < 1.0


def unit(value: Any) -> bool:
    """A number in [0, 1]."""
    return number(value) and 0.0 <= value <= 1.0


def non_negative(value: Any) -> bool:
    """A finite number >= 0."""
    return number(value) and value >= 0


def positive(value: Any) -> bool:
    """A finite number > 0."""
    return number(value) and value > 0


def switch(value: Any) -> bool:
    """``True`` or ``False`` (Hydra keeps ``no`` / ``off`` as strings, which are always true)."""
    return isinstance(value, bool)


def layers(value: Any) -> bool:
    """A list of layer sizes, each an integer >= 1."""
    return isinstance(value, (list, tuple)) and all(positive_int(v) for v in value)


def optional(check: Callable[[Any], bool]) -> Callable[[Any], bool]:
    """``check``, or ``None``."""
    return lambda value: value is None or check(value)


def list_of(check: Callable[[Any], bool], *, distinct: bool = False) -> Callable[[Any], bool]:
    """A check of a non-empty list whose items all pass ``check`` (and differ from each other with
    ``distinct``).

    Examples:
        >>> seeds = list_of(seed, distinct=True)
        >>> seeds([0, 1]), seeds([]), seeds([1, 1]), seeds(3)
        (True, False, False, False)
    """

    def accepts(value: Any) -> bool:
        return (
            isinstance(value, (list, tuple))
            and len(value) >= 1
            and all(check(v) for v in value)
            and (not distinct or len(set(value)) == len(value))
        )

    return accepts


def check_keys(cfg: Mapping, rules: Mapping[str, Rule], prefix: str = "") -> None:
    """Raise :class:`SettingsError` for the first key of ``rules`` missing from ``cfg``, or whose value its
    rule refuses (``prefix``: the dotted name of ``cfg``'s section, for the message).

    Examples:
        >>> check_keys({"seeds": []}, {"seeds": (list_of(seed), "a non-empty list of integers >= 0")})
        Traceback (most recent call last):
        ...
        spoil_torchrl.errors.SettingsError: seeds = []: expected a non-empty list of integers >= 0
    """
    for key, (check, expected) in rules.items():
        if key not in cfg:
            raise SettingsError(f"{prefix}{key} is missing: expected {expected}")
        if not check(cfg[key]):
            raise SettingsError(f"{prefix}{key} = {cfg[key]!r}: expected {expected}")


def check_section(
    cfg: Mapping,
    name: str,
    rules: Mapping[str, Rule],
    *,
    accepted: tuple[str, ...] | None = None,
    every_key: bool = True,
) -> None:
    """Check the section ``cfg[name]``: a key outside ``accepted`` (default: the keys of ``rules``) is refused,
    each key of ``rules`` it has must pass its rule, and with ``every_key`` each key of ``rules`` must be there
    (``every_key=False``: a key left out keeps its default).

    Examples:
        >>> rules = {"kappa": (open_unit, "a quantile in (0, 1)")}
        >>> check_section({"training": {"kappa": 2}}, "training", rules)
        Traceback (most recent call last):
        ...
        spoil_torchrl.errors.SettingsError: training.kappa = 2: expected a quantile in (0, 1)
        >>> check_section({"training": {"kapa": 0.1}}, "training", rules, every_key=False)
        Traceback (most recent call last):
        ...
        spoil_torchrl.errors.SettingsError: training.kapa is not a setting; the settings of training: kappa
    """
    section = cfg.get(name)
    if not isinstance(section, Mapping):
        raise SettingsError(f"{name} = {section!r}: expected a section with {', '.join(rules)}")
    allowed = tuple(rules) if accepted is None else accepted
    for key in section:
        if key not in allowed:
            raise SettingsError(
                f"{name}.{key} is not a setting; the settings of {name}: {', '.join(allowed)}"
            )
    check_keys(
        section,
        rules if every_key else {key: rule for key, rule in rules.items() if key in section},
        f"{name}.",
    )
