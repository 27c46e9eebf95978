"""The fixes :func:`spoil_torchrl.envs.compat.import_safety_gymnasium` applies to safety-gymnasium 1.0.0.

Each function fixes one break, names the upstream line it patches (paths inside the installed
``safety_gymnasium`` or ``gymnasium`` package, release 1.0.0 and 1.4.0) and changes nothing else: the
simulation, rewards and costs stay the installed MuJoCo's. Which versions need which fix is
:data:`spoil_torchrl.envs.compat.PATCHES`; a test for each (``tests/envs/test_compat.py``) shows the break
without it. Each is applied once per process.
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import numpy as np

COLOR_MODULE = "safety_gymnasium.assets.color"

#: safety-gymnasium's velocity tasks (one module per robot and version).
VELOCITY_MODULES = tuple(
    f"safety_gymnasium.tasks.safe_velocity.safety_{robot}_velocity_v{version}"
    for robot in ("ant", "half_cheetah", "hopper", "humanoid", "swimmer", "walker2d")
    for version in (0, 1)
)

#: The start of MuJoCo 3's deprecation notice for ``<compiler settotalmass>`` (printed at each model load).
SETTOTALMASS_NOTICE = "compiler attribute 'settotalmass' is deprecated"


class HashableArray(np.ndarray):
    """An ndarray view that dataclasses accept as a default (identity hash, like any plain object)."""

    __hash__ = object.__hash__


def hashable_colours() -> None:
    """Python >= 3.11 rejects unhashable dataclass defaults ("mutable default <class 'numpy.ndarray'> for field
    color is not allowed"), and safety-gymnasium's geoms declare ``color: np.array = COLOR['hazard']``
    (``assets/geoms/hazards.py:39`` and the other geoms), so ``import safety_gymnasium`` fails.

    Fix: ``assets/color.py`` is loaded first, by itself, and each colour replaced by a view of the same array
    whose class defines ``__hash__``; the module is registered under its real name, so the package imports
    the patched table. The colours, and so rendered images and vision observations, are unchanged."""
    spec = importlib.util.find_spec("safety_gymnasium")
    path = Path(spec.origin).parent / "assets" / "color.py"
    module_spec = importlib.util.spec_from_file_location(COLOR_MODULE, path)
    module = importlib.util.module_from_spec(module_spec)
    module_spec.loader.exec_module(module)
    module.COLOR = {name: np.asarray(rgba).view(HashableArray) for name, rgba in module.COLOR.items()}
    sys.modules[COLOR_MODULE] = module


class _RemovedInGymnasium1:
    """Stands in for ``gymnasium.wrappers.compatibility.EnvCompatibility``, which gymnasium 1.0 removed: the
    old four-tuple step API it converted is gone. safety-gymnasium uses it only for
    ``make(..., apply_api_compatibility=True)``; that call is refused with this message."""

    def __init__(self, *args, **kwargs) -> None:
        raise NotImplementedError(
            "apply_api_compatibility=True needs gymnasium.wrappers.EnvCompatibility, which gymnasium 1.0 removed"
        )


def wrapper_modules() -> None:
    """gymnasium 1.0 merged its wrapper modules, and ``gymnasium.wrappers.compatibility``, ``.autoreset``,
    ``.env_checker``, ``.time_limit`` and ``.normalize`` no longer exist, but safety-gymnasium imports from them
    at import time (``utils/registration.py:28``, ``wrappers/autoreset.py:18``, ``wrappers/env_checker.py:18``,
    ``wrappers/time_limit.py:18``, ``wrappers/normalize.py:20``).

    Fix: those five modules are registered with the same names bound to gymnasium 1.x's classes
    (``AutoResetWrapper`` is now ``Autoreset``; ``RunningMeanStd`` moved to ``gymnasium.wrappers.utils``).
    safety-gymnasium's subclasses use only what they kept: the step counters of ``TimeLimit`` and the
    ``checked_step`` flag of ``PassiveEnvChecker``."""
    import gymnasium.wrappers as wrappers
    from gymnasium.wrappers.utils import RunningMeanStd

    contents = {
        "compatibility": {"EnvCompatibility": _RemovedInGymnasium1},
        "autoreset": {"AutoResetWrapper": wrappers.Autoreset},
        "env_checker": {"PassiveEnvChecker": wrappers.PassiveEnvChecker},
        "time_limit": {"TimeLimit": wrappers.TimeLimit},
        "normalize": {
            "NormalizeObservation": wrappers.NormalizeObservation,
            "NormalizeReward": wrappers.NormalizeReward,
            "RunningMeanStd": RunningMeanStd,
        },
    }
    for name, attributes in contents.items():
        full = f"gymnasium.wrappers.{name}"
        if full not in sys.modules:
            module = ModuleType(full, f"gymnasium 0.29's {full}, as spoil_torchrl maps it onto gymnasium 1.x")
            module.__dict__.update(attributes)
            sys.modules[full] = module


class _EnvSpecFactory(type):
    """``EnvSpec`` as safety-gymnasium's registration module sees it: ``isinstance`` is gymnasium's, and a
    call drops the two fields gymnasium 1.0 removed."""

    def __instancecheck__(cls, instance) -> bool:
        from gymnasium.envs.registration import EnvSpec

        return isinstance(instance, EnvSpec)

    def __call__(cls, *args, autoreset=None, apply_api_compatibility=None, **kwargs):
        from gymnasium.envs.registration import EnvSpec

        return EnvSpec(*args, **kwargs)


class _EnvSpec(metaclass=_EnvSpecFactory):
    pass


def envspec_fields() -> None:
    """gymnasium 1.0 removed ``EnvSpec.autoreset`` and ``EnvSpec.apply_api_compatibility``.
    safety-gymnasium's ``make`` builds an ``EnvSpec`` with both (``utils/registration.py:160-173``), a
    ``TypeError``, and reads them when the caller leaves them unset (``utils/registration.py:139-140``,
    ``191-192`` and ``213``), an ``AttributeError``.

    Fix: in that module only, ``EnvSpec`` drops the two fields, and ``make`` treats unset as ``False``, their
    default in gymnasium 0.29 (no task of safety-gymnasium registers either as true)."""
    registration = importlib.import_module("safety_gymnasium.utils.registration")
    package = sys.modules["safety_gymnasium"]
    original = registration.make
    registration.EnvSpec = _EnvSpec

    @functools.wraps(original)
    def make(id, max_episode_steps=None, autoreset=None, apply_api_compatibility=None, **kwargs):  # noqa: A002
        return original(
            id,
            max_episode_steps=max_episode_steps,
            autoreset=bool(autoreset),
            apply_api_compatibility=bool(apply_api_compatibility),
            **kwargs,
        )

    registration.make = package.make = make


def _as_array_first(method):
    @functools.wraps(method)
    def wrapper(self, action, *args, **kwargs):
        return method(self, np.asarray(action), *args, **kwargs)

    return wrapper


def array_copy() -> None:
    """NumPy 2 made ``np.array(x, copy=False)`` mean "never copy", so it raises for a list or any action that
    needs converting; safety-gymnasium casts every action that way (``builder.py:195`` in ``Builder.step``,
    ``bases/base_agent.py:311`` in ``BaseAgent.apply_action``).

    Fix: both methods receive ``np.asarray(action)``, which NumPy 1's ``copy=False`` amounted to."""
    builder = importlib.import_module("safety_gymnasium.builder")
    base_agent = importlib.import_module("safety_gymnasium.bases.base_agent")
    builder.Builder.step = _as_array_first(builder.Builder.step)
    base_agent.BaseAgent.apply_action = _as_array_first(base_agent.BaseAgent.apply_action)


def box_overflow() -> None:
    """Under NumPy 2, gymnasium's ``Box`` compares float32 bounds with float64's range, and the cast overflows:
    "RuntimeWarning: overflow encountered in cast" (``gymnasium/spaces/box.py:288`` and ``:355``) at every
    navigation-task build, from the action space safety-gymnasium makes of float32 bounds with
    ``dtype=np.float64`` (``bases/base_agent.py:232-234``). The space is right; the warning is noise.

    Fix: ``BaseAgent._build_action_space`` runs with NumPy's overflow warnings off (nothing else it computes
    can overflow: it reads the actuators' control ranges)."""
    base_agent = importlib.import_module("safety_gymnasium.bases.base_agent")
    original = base_agent.BaseAgent._build_action_space

    @functools.wraps(original)
    def build(self):
        with np.errstate(over="ignore"):
            return original(self)

    base_agent.BaseAgent._build_action_space = build


@functools.cache
def _velocity_classes() -> tuple[type, ...]:
    """safety-gymnasium's velocity-task classes (found once; three patches wrap them)."""
    classes = []
    for name in VELOCITY_MODULES:
        module = importlib.import_module(name)
        classes += [
            obj
            for key, obj in vars(module).items()
            if key.startswith("Safety") and isinstance(obj, type) and obj.__module__ == name
        ]
    return tuple(classes)


def _filter_mujoco_warnings(drop: str):
    """A MuJoCo warning callback that drops messages starting with ``drop`` and passes on the others."""
    import mujoco

    previous = mujoco.get_mju_user_warning()

    def callback(message: str) -> None:
        if message.startswith(drop):
            return
        if previous is not None:
            previous(message)
        else:  # MuJoCo's own default
            print(f"WARNING: {message}\n", file=sys.stderr)

    return previous, callback


def settotalmass_notice() -> None:
    """MuJoCo 3 prints "WARNING: compiler attribute 'settotalmass' is deprecated ..." to stderr whenever a
    model with ``<compiler settotalmass>`` is compiled: gymnasium's ``envs/mujoco/assets/half_cheetah.xml``
    (line 9), which every HalfCheetah velocity task loads, once per environment. MuJoCo still applies the
    attribute, so the masses are unchanged; the notice concerns gymnasium's file, not our user.

    Fix: while a velocity task is built, MuJoCo's warning callback drops that one notice and passes every other
    warning on."""
    import mujoco

    for cls in _velocity_classes():
        original = cls.__init__

        @functools.wraps(original)
        def init(self, *args, _original=original, **kwargs):
            previous, callback = _filter_mujoco_warnings(SETTOTALMASS_NOTICE)
            mujoco.set_mju_user_warning(callback)
            try:
                _original(self, *args, **kwargs)
            finally:
                mujoco.set_mju_user_warning(previous)

        cls.__init__ = init


def quaternion_reset() -> None:
    """From MuJoCo 3.2, ``mj_forward`` no longer normalises the quaternions of ``qpos`` in place. gymnasium's
    ``MujocoEnv.set_state`` (``envs/mujoco/mujoco_env.py``, ``set_state``) writes ``qpos`` and calls it, and the
    Ant and Humanoid velocity tasks reset with noise added to their free joint's quaternion
    (``reset_model``), so their first observation holds a quaternion of norm != 1 (Ant: off by up to 0.09
    against MuJoCo 2.3).

    Fix: the velocity tasks' ``set_state`` normalises the quaternions first (``mujoco.mj_normalizeQuat``), as
    MuJoCo 2.3 did; for tasks without free or ball joints it changes nothing."""
    import mujoco

    for cls in _velocity_classes():
        original = cls.set_state

        @functools.wraps(original)
        def set_state(self, qpos, qvel, _original=original):
            qpos = np.array(qpos, dtype=np.float64)
            mujoco.mj_normalizeQuat(self.model, qpos)
            return _original(self, qpos, qvel)

        cls.set_state = set_state


def offscreen_size() -> None:
    """gymnasium 1.0's ``OffScreenViewer(model, data, width, height)`` requires the image size, but
    safety-gymnasium's navigation tasks build it with two arguments (``bases/underlying.py:568``), so
    ``render()`` raises a ``TypeError``.

    Fix: that module's ``OffScreenViewer`` passes the size safety-gymnasium already set as the model's offscreen
    buffer (``bases/underlying.py:491-492``: ``model.vis.global_.offwidth`` / ``offheight``)."""
    underlying = importlib.import_module("safety_gymnasium.bases.underlying")
    viewer = underlying.OffScreenViewer

    def offscreen_viewer(model, data, width=None, height=None, **kwargs):
        width = model.vis.global_.offwidth if width is None else width
        height = model.vis.global_.offheight if height is None else height
        return viewer(model, data, width, height, **kwargs)

    underlying.OffScreenViewer = offscreen_viewer


def track_camera() -> None:
    """gymnasium 1.x's ``MujocoRenderer`` renders from the free camera when no camera is named
    (``envs/mujoco/mujoco_rendering.py:751-767``), where 0.29 used the model's ``track`` camera, which follows
    the robot; a velocity task's frames then lose the robot as it runs away.

    Fix: the velocity tasks default to ``camera_name="track"`` when neither ``camera_name`` nor ``camera_id``
    is given (their models all have that camera)."""
    for cls in _velocity_classes():
        original = cls.__init__

        @functools.wraps(original)
        def init(self, *args, _original=original, **kwargs):
            if kwargs.get("camera_name") is None and kwargs.get("camera_id") is None:
                kwargs["camera_name"] = "track"
            _original(self, *args, **kwargs)

        cls.__init__ = init
