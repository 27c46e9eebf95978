"""Importing safety-gymnasium 1.0.0 on Python >= 3.11, and an optional fast reset.

**The upstream problem.** safety-gymnasium 1.0.0 (its latest release, 2023) declares dataclass fields whose
defaults are NumPy arrays taken from ``safety_gymnasium/assets/color.py`` (e.g. ``color: np.ndarray =
COLOR['hazard']``). Python 3.11 made ``dataclasses`` reject unhashable defaults ("mutable default <class
'numpy.ndarray'> for field color is not allowed: use default_factory"), so ``import safety_gymnasium`` fails
there; the same error breaks safety-gymnasium 0.4 and with it the ``dsrl`` package. (Its ``group.py`` table
holds ints and needs nothing.)

**The fix.** Before the package is imported, :func:`import_safety_gymnasium` loads ``assets/color.py`` by
itself and replaces each colour by a view of the same array whose class defines ``__hash__``. The arrays, and
so the rendered colours and the vision observations, are unchanged; rewards and costs are identical to a
Python 3.10 run (measured). The module is registered in ``sys.modules`` under its real name, so
the package then imports the patched table.

**Fast reset (rendering only).** Navigation tasks rebuild their MuJoCo model at every reset and decode a 24 MB
star-field skybox PNG each time (about 0.6 s per reset). :func:`enable_fast_reset` makes the world builder use
a built-in gradient skybox instead. Physics, observations of the non-vision tasks, rewards and costs do not
depend on the skybox; only rendered images change. It is on for headless collection and evaluation.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import numpy as np

COLOR_MODULE = "safety_gymnasium.assets.color"
INSTALL_HINT = (
    "safety-gymnasium is not installed. `make setup` installs it (see CONTRIBUTING.md: it needs gymnasium "
    "0.29.1, mujoco 2.3.7 and numpy 1.26, then `pip install --no-deps safety-gymnasium==1.0.0`)"
)


class HashableArray(np.ndarray):
    """An ndarray view that dataclasses accept as a default (identity hash, like any plain object)."""

    __hash__ = object.__hash__


def _preload_hashable_colors() -> None:
    spec = importlib.util.find_spec("safety_gymnasium")
    if spec is None or spec.origin is None:
        raise ImportError(INSTALL_HINT)
    path = Path(spec.origin).parent / "assets" / "color.py"
    module_spec = importlib.util.spec_from_file_location(COLOR_MODULE, path)
    module = importlib.util.module_from_spec(module_spec)
    module_spec.loader.exec_module(module)
    module.COLOR = {name: np.asarray(rgba).view(HashableArray) for name, rgba in module.COLOR.items()}
    sys.modules[COLOR_MODULE] = module


def import_safety_gymnasium() -> ModuleType:
    """``import safety_gymnasium``, working around its Python >= 3.11 dataclass error (see module docstring).

    Raises ``ImportError`` with install instructions when the package is missing.
    """
    if "safety_gymnasium" in sys.modules:
        return sys.modules["safety_gymnasium"]
    if sys.version_info >= (3, 11) and COLOR_MODULE not in sys.modules:
        _preload_hashable_colors()
    try:
        return importlib.import_module("safety_gymnasium")
    except ImportError as err:
        raise ImportError(f"{INSTALL_HINT} ({err})") from err


class _FastSkyboxYaml:
    """Stands in for the ``yaml`` module inside ``safety_gymnasium.world``: parses ``assets.yaml`` once and
    swaps the star-field skybox files for MuJoCo's built-in gradient."""

    def __init__(self, yaml_module: ModuleType) -> None:
        self._yaml = yaml_module
        self.FullLoader = yaml_module.FullLoader
        self._cache: dict[str, object] = {}

    def load(self, stream, Loader=None):  # noqa: N803 - yaml's signature
        name = getattr(stream, "name", None)
        if name is None or not str(name).endswith("assets.yaml"):
            return self._yaml.load(stream, Loader=Loader)
        if name not in self._cache:
            config = self._yaml.load(stream, Loader=Loader)
            config["textures"]["skybox"] = {
                "@type": "skybox",
                "@builtin": "gradient",
                "@rgb1": ".4 .6 .8",
                "@rgb2": "0 0 0",
                "@width": "32",
                "@height": "32",
            }
            self._cache[name] = config
        import copy

        return copy.deepcopy(self._cache[name])

    def __getattr__(self, item):
        return getattr(self._yaml, item)


def enable_fast_reset() -> None:
    """Make navigation-task resets skip the 24 MB skybox PNG (rendering only; see module docstring)."""
    import_safety_gymnasium()
    world = importlib.import_module("safety_gymnasium.world")
    if not isinstance(world.yaml, _FastSkyboxYaml):
        world.yaml = _FastSkyboxYaml(world.yaml)


def disable_fast_reset() -> None:
    """Undo :func:`enable_fast_reset` (the original star-field skybox is loaded again)."""
    world = sys.modules.get("safety_gymnasium.world")
    if world is not None and isinstance(world.yaml, _FastSkyboxYaml):
        world.yaml = world.yaml._yaml


def fast_reset_enabled() -> bool:
    """Whether :func:`enable_fast_reset` is in effect."""
    world = sys.modules.get("safety_gymnasium.world")
    return world is not None and isinstance(world.yaml, _FastSkyboxYaml)
