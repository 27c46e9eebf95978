"""The software stack a dataset or a run was made on, and how two stacks differ.

The simulators' physics change between MuJoCo releases (minor releases included), so the same policy, seed and
task give other episodes on another stack. Every dataset this project writes and every ``results.json``
therefore records :func:`current_stack`: the versions of the packages that decide what a rollout or an update
computes. A cached dataset from another stack is made again (:func:`spoil_torchrl.data.ensure_generated`), a
run does not resume on another stack, and ``spoil-report`` warns when a table mixes stacks.

Two stacks are supported (``docs/usage.md``, "Stacks"): the default (gymnasium 1.x, mujoco 3, numpy 2) and
``legacy`` (gymnasium 0.29.1, mujoco 2.3.7, numpy 1.26.4), which reproduces the results committed before the
default changed.

Examples:
    >>> a = {"mujoco": "2.3.7", "gymnasium": "0.29.1", "numpy": "1.26.4", "torch": "2.13.0+cpu"}
    >>> b = dict(a, mujoco="3.17.0", numpy="2.4.6")
    >>> stack_differences(a, b)
    ['mujoco 2.3.7 / 3.17.0', 'numpy 1.26.4 / 2.4.6']
    >>> stack_label(b)
    'mujoco 3.17.0, gymnasium 0.29.1, numpy 2.4.6, torch 2.13.0+cpu'
    >>> stack_name(a), stack_name(b)
    ('legacy', 'other')
"""

from __future__ import annotations

import platform
from collections.abc import Mapping
from importlib import metadata

__all__ = [
    "DEFAULT_STACK",
    "LEGACY_STACK",
    "STACK_PACKAGES",
    "current_machine",
    "current_stack",
    "stack_differences",
    "stack_label",
    "stack_name",
]

#: The packages whose versions decide a rollout's or an update's numbers (distribution names).
STACK_PACKAGES = ("mujoco", "gymnasium", "numpy", "torch", "safety-gymnasium")

#: The stack every result committed before the default changed was made on (``STACK=legacy``).
LEGACY_STACK = {"mujoco": "2.3.7", "gymnasium": "0.29.1", "numpy": "1.26.4"}

#: The default stack of ``make`` and of the ``safety`` extra (``pyproject.toml``).
DEFAULT_STACK = {"mujoco": "3.17.0", "gymnasium": "1.4.0", "numpy": "2.4.6"}


def current_stack() -> dict[str, str | None]:
    """The installed versions of :data:`STACK_PACKAGES` (``None`` for one that is not installed) and Python's.

    Read from the packages' metadata: nothing is imported.
    """
    stack: dict[str, str | None] = {}
    for name in STACK_PACKAGES:
        try:
            stack[name.replace("-", "_")] = metadata.version(name)
        except metadata.PackageNotFoundError:
            stack[name.replace("-", "_")] = None
    stack["python"] = platform.python_version()
    return stack


def current_machine() -> dict[str, str]:
    """Where this process runs: the host's name and the CPU's model (``/proc/cpuinfo``'s ``model name`` on
    Linux, else :func:`platform.processor`). Two machines with one stack may still round floating point
    differently (another CPU takes other BLAS kernels), so a run records where each of its parts ran.

    Examples:
        >>> sorted(current_machine())
        ['cpu', 'host']
    """
    cpu = ""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), "")
    except OSError:
        pass
    return {"host": platform.node(), "cpu": cpu or platform.processor() or platform.machine()}


def stack_differences(recorded: Mapping | None, current: Mapping | None = None) -> list[str]:
    """``"<package> <recorded> / <current>"`` for each compared package whose versions differ (Python left
    out: it does not change the numbers by itself). ``current`` defaults to :func:`current_stack`.

    A record without a stack (made before records carried one) differs in every package.
    """
    current = current_stack() if current is None else current
    recorded = recorded or {}
    out = []
    for name in (n.replace("-", "_") for n in STACK_PACKAGES):
        if name in current and recorded.get(name) != current.get(name):
            out.append(f"{name} {recorded.get(name, 'unrecorded')} / {current.get(name)}")
    return out


def stack_label(stack: Mapping | None) -> str:
    """A short text naming a stack's simulator, gymnasium, numpy and torch versions."""
    if not stack:
        return "unrecorded stack"
    return ", ".join(f"{name} {stack.get(name)}" for name in ("mujoco", "gymnasium", "numpy", "torch"))


def stack_name(stack: Mapping | None) -> str:
    """``"default"`` or ``"legacy"`` when a stack's simulator, gymnasium and numpy are one of the two
    supported stacks, ``"unrecorded"`` for no record, else ``"other"``."""
    if not stack:
        return "unrecorded"
    for name, pins in (("default", DEFAULT_STACK), ("legacy", LEGACY_STACK)):
        if all(stack.get(k) == v for k, v in pins.items()):
            return name
    return "other"
