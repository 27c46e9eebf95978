"""Importing safety-gymnasium 1.0.0 on today's stack: the patches, each gated on the version that needs it.

safety-gymnasium's only release (1.0.0, 2023) was written against gymnasium 0.28 / 0.29, MuJoCo 2.3, NumPy 1
and Python 3.10. :func:`import_safety_gymnasium` imports it with the patches of :data:`PATCHES` that the
installed versions need (each one's gate), so that the same package works on the default stack (gymnasium
1.x, MuJoCo 3, NumPy 2) and on the legacy one. On the legacy stack (gymnasium 0.29.1, MuJoCo 2.3.7, NumPy
1.26.4, Python 3.11) only the first applies. Every patch leaves the physics, rewards and costs of the task as
the installed simulator computes them; what each one fixes, and the upstream line it patches, is in
:mod:`spoil_torchrl.envs.patches` and in ``docs/usage.md`` ("Stacks").

``SPOIL_TORCHRL_SKIP_PATCHES=<name>[,<name>...]`` leaves patches out (for checking that a patch is still
needed; the tests do it in a fresh process).

Example:
    >>> [(patch.name, patch.gate) for patch in PATCHES[:2]]
    [('hashable-colours', 'Python >= 3.11'), ('wrapper-modules', 'gymnasium >= 1.0')]
    >>> needed = [patch.name for patch in needed_patches()]  # what ``import_safety_gymnasium()`` applies here
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata
from types import ModuleType

from packaging.version import Version

from spoil_torchrl.envs import patches

__all__ = ["INSTALL_HINT", "PATCHES", "Patch", "applied_patches", "import_safety_gymnasium", "needed_patches"]

INSTALL_HINT = (
    "safety-gymnasium is not installed. `make setup` installs it (CONTRIBUTING.md, 'Stacks': the `safety` "
    "extra, then `pip install --no-deps safety-gymnasium==1.0.0`, which would otherwise pin gymnasium 0.28.1)"
)

#: Names of the patches to leave out, comma-separated (tests only).
SKIP_ENV = "SPOIL_TORCHRL_SKIP_PATCHES"


def installed_version(distribution: str) -> Version | None:
    """The installed version of ``distribution`` (``None`` when it is not installed)."""
    try:
        return Version(metadata.version(distribution))
    except metadata.PackageNotFoundError:
        return None


def _at_least(distribution: str, version: str) -> Callable[[], bool]:
    def gate() -> bool:
        found = installed_version(distribution)
        return found is not None and found >= Version(version)

    gate.__doc__ = f"{distribution} >= {version}"
    return gate


def _python_at_least(major: int, minor: int) -> Callable[[], bool]:
    def gate() -> bool:
        return sys.version_info >= (major, minor)

    gate.__doc__ = f"Python >= {major}.{minor}"
    return gate


@dataclass(frozen=True)
class Patch:
    """One fix of safety-gymnasium 1.0.0 for a newer dependency.

    Attributes:
        name: what ``SPOIL_TORCHRL_SKIP_PATCHES`` and :func:`applied_patches` call it.
        needed: the gate: true when the installed version has the break.
        apply: the fix (``before_import``: run before ``import safety_gymnasium``, else after it).
        before_import: whether the package cannot be imported without it.
    """

    name: str
    needed: Callable[[], bool]
    apply: Callable[[], None]
    before_import: bool = False

    @property
    def gate(self) -> str:
        return self.needed.__doc__ or ""


#: The patches, in the order they are applied (docstrings of :mod:`spoil_torchrl.envs.patches`).
PATCHES: tuple[Patch, ...] = (
    Patch("hashable-colours", _python_at_least(3, 11), patches.hashable_colours, before_import=True),
    Patch("wrapper-modules", _at_least("gymnasium", "1.0"), patches.wrapper_modules, before_import=True),
    Patch("envspec-fields", _at_least("gymnasium", "1.0"), patches.envspec_fields),
    Patch("array-copy", _at_least("numpy", "2.0"), patches.array_copy),
    Patch("box-overflow", _at_least("numpy", "2.0"), patches.box_overflow),
    Patch("settotalmass-notice", _at_least("mujoco", "3.0"), patches.settotalmass_notice),
    Patch("quaternion-reset", _at_least("mujoco", "3.2"), patches.quaternion_reset),
    Patch("offscreen-size", _at_least("gymnasium", "1.0"), patches.offscreen_size),
    Patch("track-camera", _at_least("gymnasium", "1.0"), patches.track_camera),
)

_APPLIED: list[str] = []
_IMPORTED: list[ModuleType] = []  # the patched module, once imported


def needed_patches() -> list[Patch]:
    """The patches the installed versions need, less those named in ``SPOIL_TORCHRL_SKIP_PATCHES``."""
    skip = {name.strip() for name in os.environ.get(SKIP_ENV, "").split(",") if name.strip()}
    unknown = skip - {p.name for p in PATCHES}
    if unknown:
        raise ValueError(f"{SKIP_ENV}: unknown patch {sorted(unknown)}; known: {[p.name for p in PATCHES]}")
    return [p for p in PATCHES if p.name not in skip and p.needed()]


def applied_patches() -> list[str]:
    """The names of the patches :func:`import_safety_gymnasium` applied in this process.

    Examples:
        >>> _ = import_safety_gymnasium()
        >>> applied_patches() == [patch.name for patch in needed_patches()]  # those this stack needs
        True
        >>> "hashable-colours" in applied_patches()  # needed from Python 3.11 on
        True
    """
    return list(_APPLIED)


def import_safety_gymnasium() -> ModuleType:
    """``import safety_gymnasium`` with the patches the installed stack needs (see module docstring).

    Raises ``ImportError`` with install instructions when the package is missing.

    Examples:
        >>> safety_gymnasium = import_safety_gymnasium()
        >>> env = safety_gymnasium.make("SafetyHopperVelocity-v1")
        >>> obs, info = env.reset(seed=0)
        >>> obs, reward, cost, terminated, truncated, info = env.step(env.action_space.sample())  # six values
        >>> obs.shape, type(cost)
        ((11,), <class 'float'>)
        >>> import_safety_gymnasium() is safety_gymnasium  # imported and patched once per process
        True
    """
    if _IMPORTED:
        return _IMPORTED[0]
    if importlib.util.find_spec("safety_gymnasium") is None:
        raise ImportError(INSTALL_HINT)
    todo = needed_patches()
    for patch in (p for p in todo if p.before_import and p.name not in _APPLIED):
        patch.apply()
        _APPLIED.append(patch.name)
    try:
        module = importlib.import_module("safety_gymnasium")
    except ImportError as err:
        raise ImportError(f"{INSTALL_HINT} ({err})") from err
    for patch in (p for p in todo if not p.before_import and p.name not in _APPLIED):
        patch.apply()
        _APPLIED.append(patch.name)
    _IMPORTED.append(module)
    return module
