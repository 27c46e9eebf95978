"""What a rollout file shows of the simulator: control timestep, agent pose, constraint geometry, frames.

Read from the Safety-Gymnasium 1.0.0 environment instances (never typed in):

* :func:`control_timestep`: the seconds of simulation per environment step. Navigation tasks (``Builder``) step
  MuJoCo ``frameskip_binom_n`` times (with ``frameskip_binom_p = 1``) at ``model.opt.timestep``:
  10 x 0.002 s = 0.02 s for PointCircle; gymnasium's MuJoCo tasks (the velocity tasks) have ``dt``
  (``frame_skip x timestep``, 5 x 0.01 s = 0.05 s for HalfCheetah).
* :func:`agent_pose`: position and orientation of the agent's body from MuJoCo's data (``xpos``, ``xquat``):
  the ``agent`` body of navigation tasks (what ``task.agent.pos`` / ``.mat`` read), the ``torso`` (root) body
  of the velocity tasks (x / z and pitch in the x-z plane for HalfCheetah).
* :func:`constraint_scene`: the Circle tasks' reward circle (``task.circle``: radius 1.5 at the origin) and
  their boundary walls (``task.sigwalls``: ``num`` walls at ``|x| = locate_factor`` = 1.125, and
  ``|y| = 1.125`` for Circle2; cost 1 beyond them), as Foxglove scene entities. Velocity tasks have no spatial
  boundary: no entities.

:func:`replay_episodes` gives these per step for episodes that :func:`spoil_torchrl.envs.rollout.rollout`
returned: it replays each episode's stored actions from the same reset seeds (MuJoCo is deterministic) and
checks that the replay reproduces the stored observations step by step.
"""

from __future__ import annotations

import functools
import math
import os
import warnings
from dataclasses import dataclass

import numpy as np

from spoil_torchrl.envs.rollout import episode_bounds, reset_seed
from spoil_torchrl.eval import mcap_foxglove as fox

WALL_COLOR = fox.color(0.9, 0.2, 0.2, 0.35)
CIRCLE_COLOR = fox.color(0.2, 0.8, 0.3, 1.0)


def control_timestep(env) -> float:
    """Seconds of simulation per step of a (wrapped) Safety-Gymnasium environment."""
    base = env.unwrapped
    task = getattr(base, "task", None)
    if task is not None:  # navigation tasks: physics steps per env step x MuJoCo timestep
        conf = task.sim_conf
        if conf.frameskip_binom_p != 1.0:
            raise ValueError(
                f"{type(task).__name__}: the frame skip is random (binomial n={conf.frameskip_binom_n}, "
                f"p={conf.frameskip_binom_p}), so steps have no fixed duration"
            )
        return float(conf.frameskip_binom_n * task.model.opt.timestep)
    if hasattr(base, "dt"):  # gymnasium MujocoEnv
        return float(base.dt)
    raise TypeError(f"{type(base).__name__}: no control timestep found (neither a task's sim_conf nor dt)")


def _body(env):
    base = env.unwrapped
    task = getattr(base, "task", None)
    if task is not None:
        return task.data.body("agent")
    names = [base.model.body(i).name for i in range(base.model.nbody)]
    return base.data.body("torso" if "torso" in names else names[1])


def agent_pose(env) -> np.ndarray:
    """The agent body's world position and orientation: ``[x, y, z, qx, qy, qz, qw]`` (float64)."""
    body = _body(env)
    w, x, y, z = body.xquat  # MuJoCo stores w first; Foxglove wants x, y, z, w
    return np.array([*body.xpos, x, y, z, w], dtype=np.float64)


def constraint_scene(env) -> list[dict]:
    """The task's constraint geometry as scene entities (see :func:`~spoil_torchrl.eval.mcap_foxglove.scene_update`)."""
    task = getattr(env.unwrapped, "task", None)
    entities = []
    circle = getattr(task, "circle", None)
    if circle is not None:
        cx, cy = (float(v) for v in circle.pos[:2])
        angles = np.linspace(0.0, 2 * math.pi, 64, endpoint=False)
        points = [
            {"x": cx + circle.radius * math.cos(a), "y": cy + circle.radius * math.sin(a), "z": 0.01}
            for a in angles
        ]
        line = {
            "type": 1,  # LINE_LOOP
            "pose": fox.identity_pose(),
            "thickness": 0.03,
            "scale_invariant": False,
            "points": points,
            "color": CIRCLE_COLOR,
            "colors": [],
            "indices": [],
        }
        entities.append({"id": "reward_circle", "primitives": {"lines": [line]}})
    walls = getattr(task, "sigwalls", None)
    if walls is not None:
        limit, half = float(walls.locate_factor), float(walls.size)
        cubes = []
        for i, (x, y) in enumerate(walls.locations[: walls.num]):  # walls 2, 3 are turned by 90 degrees
            size = {"x": 0.1, "y": 2 * half, "z": 0.6} if i < 2 else {"x": 2 * half, "y": 0.1, "z": 0.6}
            cubes.append({"pose": fox.identity_pose(x, y, 0.25), "size": size, "color": WALL_COLOR})
        entities.append({"id": f"boundary_walls_at_{limit:g}", "primitives": {"cubes": cubes}})
    return entities


@dataclass(frozen=True)
class TaskView:
    """A task's :func:`control_timestep` and :func:`constraint_scene`."""

    dt: float
    scene: tuple[dict, ...]


@functools.cache
def task_view(env_id: str) -> TaskView:
    """:class:`TaskView` of a task of :data:`spoil_torchrl.tasks.ENV_TASKS` (made once per process)."""
    from spoil_torchrl.envs import make_safety_gymnasium

    env = make_safety_gymnasium(env_id)
    try:
        env.reset(seed=0)
        return TaskView(control_timestep(env), tuple(constraint_scene(env)))
    finally:
        env.close()


def make_render_env(env_id: str, size: int):
    """The task's environment rendering ``size x size`` RGB frames, checked by rendering one.

    Without a display, MuJoCo needs an off-screen OpenGL context: ``MUJOCO_GL=egl`` is set when
    ``MUJOCO_GL`` is unset (Mesa's or a GPU's EGL); ``MUJOCO_GL=osmesa`` works where OSMesa is installed.

    Raises:
        RuntimeError: rendering does not work here, with what to do.
    """
    from spoil_torchrl.envs import make_safety_gymnasium

    if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
        os.environ["MUJOCO_GL"] = "egl"
    env = make_safety_gymnasium(env_id, render_mode="rgb_array", width=int(size), height=int(size))
    try:
        env.reset(seed=0)
        frame = env.render()
        if not isinstance(frame, np.ndarray) or frame.shape != (size, size, 3):
            raise RuntimeError(f"render() returned {type(frame).__name__} {getattr(frame, 'shape', '')}")
    except Exception as err:
        env.close()
        raise RuntimeError(
            f"{env_id}: rendering frames does not work here ({type(err).__name__}: {err}). MuJoCo needs an "
            f"OpenGL context; without a display set MUJOCO_GL=egl or MUJOCO_GL=osmesa (now "
            f"{os.environ.get('MUJOCO_GL')!r}) before starting, or switch frames off (eval.frames=false)"
        ) from err
    return env


def replay_episodes(
    env_id: str, arrays, *, seed: int, num_envs: int, frames: bool = False, frame_size: int = 256
) -> tuple[list[np.ndarray | None], list[list[np.ndarray] | None]]:
    """Per-step agent poses (``[T, 7]``, see :func:`agent_pose`) and, with ``frames``, rendered frames of the
    episodes ``rollout(env_id, ..., seed=seed, num_envs=num_envs)`` returned as ``arrays`` (in their order).

    Environment ``i`` of the rollout was reset with its own seed, then unseeded for its later episodes; each
    reset's observation identifies the episode that followed it. An episode whose replay does not reproduce
    its stored observations gets ``None`` (with a warning).
    """
    from spoil_torchrl.envs import make_safety_gymnasium

    bounds = list(zip(*(b.tolist() for b in episode_bounds(arrays)), strict=True))
    obs, next_obs = np.asarray(arrays["observations"]), np.asarray(arrays["next_observations"])
    actions = np.asarray(arrays["actions"], dtype=np.float64)
    poses: list[np.ndarray | None] = [None] * len(bounds)
    images: list[list[np.ndarray] | None] = [None] * len(bounds)
    remaining = list(range(len(bounds)))
    env = make_render_env(env_id, frame_size) if frames else make_safety_gymnasium(env_id)
    try:
        for i in range(min(num_envs, len(bounds))):
            first = env.reset(seed=reset_seed(seed, i))[0]
            while True:
                match = [e for e in remaining if np.array_equal(obs[bounds[e][0]], first.astype(np.float32))]
                if not match:
                    break
                e = match[0]
                remaining.remove(e)
                start, end = bounds[e]
                trace, shots, ok = [], [], True
                for row in range(start, end):
                    trace.append(agent_pose(env))
                    if frames:
                        shots.append(env.render())
                    reached = env.step(actions[row])[0]
                    ok = ok and np.array_equal(reached.astype(np.float32), next_obs[row])
                if ok:
                    poses[e], images[e] = np.stack(trace), (shots if frames else None)
                else:
                    warnings.warn(
                        f"{env_id}: the replay of episode {e} left its stored trajectory; it has no poses",
                        stacklevel=2,
                    )
                first = env.reset()[0]
    finally:
        env.close()
    if remaining:
        warnings.warn(f"{env_id}: {len(remaining)} episode(s) were not found in the replay", stacklevel=2)
    return poses, images
