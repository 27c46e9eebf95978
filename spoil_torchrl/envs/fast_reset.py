"""Fast reset of the navigation tasks (rendering only).

Navigation tasks rebuild their MuJoCo model at every reset and decode a 24 MB star-field skybox PNG each time
(about 0.6 s per reset). :func:`enable_fast_reset` makes safety-gymnasium's world builder use MuJoCo's
built-in gradient skybox instead. Physics, observations of the non-vision tasks, rewards and costs do not
depend on the skybox; only rendered images change. It is on for headless collection and evaluation.

Example:
    >>> enable_fast_reset(); fast_reset_enabled()
    True
    >>> disable_fast_reset(); fast_reset_enabled()
    False
"""

from __future__ import annotations

import copy
import importlib
import sys
from types import ModuleType

from spoil_torchrl.envs.compat import import_safety_gymnasium


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
        return copy.deepcopy(self._cache[name])

    def __getattr__(self, item):
        return getattr(self._yaml, item)


def enable_fast_reset() -> None:
    """Make navigation-task resets skip the 24 MB skybox PNG (rendering only; see module docstring).

    Examples:
        >>> enable_fast_reset()
        >>> fast_reset_enabled()
        True
        >>> safety_gymnasium = import_safety_gymnasium()
        >>> obs, info = safety_gymnasium.make("SafetyPointCircle1-v0").reset(seed=0)  # some 20 ms, not 0.6 s
        >>> obs.shape
        (28,)
    """
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
    """Whether :func:`enable_fast_reset` is in effect.

    Examples:
        >>> from spoil_torchrl.envs import make_safety_gymnasium
        >>> env = make_safety_gymnasium("SafetyPointCircle1-v0", fast_reset=False)
        >>> fast_reset_enabled()
        False
        >>> env = make_safety_gymnasium("SafetyPointCircle1-v0")  # the default: fast_reset=True
        >>> fast_reset_enabled()
        True
    """
    world = sys.modules.get("safety_gymnasium.world")
    return world is not None and isinstance(world.yaml, _FastSkyboxYaml)
