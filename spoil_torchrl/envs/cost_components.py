"""A task's cost split into its constraints' own costs, read from the simulator after each step.

Safety-Gymnasium computes a task's cost from several geometric constraints and reports their union:
SafetyPointCircle2's is 1 whenever the agent is outside ``|x| <= 1.125`` *or* outside ``|y| <= 1.125`` (its
``Sigwalls`` with four walls, ``cost_out_of_boundary``). A task listed in :data:`COST_COMPONENTS` also gives each
constraint's own cost, computed from the same state the simulator's cost is computed from (the agent's position
after the step), so that data collected in it can carry one cost per constraint
(:func:`~spoil_torchrl.envs.rollout.rollout` with ``components=``, ``cost_<name>`` arrays in the file;
``docs/several_constraints.md``).
"""

from __future__ import annotations

from collections.abc import Callable

#: The prefix of a constraint's own cost, in rollout arrays and in a DSRL-layout file (``cost_<name>``).
COMPONENT_PREFIX = "cost_"


#: The constraints of a ``Sigwalls`` task, in :func:`boundary_walls`' order.
WALLS = ("x_wall", "y_wall")


def boundary_walls(env) -> dict[str, float]:
    """The two walls of a ``Sigwalls`` task as two constraints, after the step just taken: ``x_wall`` is 1 outside
    ``|x| <= locate_factor``, ``y_wall`` outside ``|y| <= locate_factor`` (0 with two walls only). The task's own
    cost is their maximum."""
    task = env.unwrapped.task
    walls, position = task.sigwalls, task.agent.pos
    limit = walls.locate_factor
    outside = (abs(position[0]) > limit, walls.num == 4 and abs(position[1]) > limit)
    return {name: float(out) for name, out in zip(WALLS, outside, strict=True)}


#: env id -> the function giving the per-constraint costs of the step just taken (module-level: rollout jobs
#: are pickled to worker processes).
COST_COMPONENTS: dict[str, Callable[[object], dict[str, float]]] = {
    "SafetyPointCircle2-v0": boundary_walls,
}


#: env id -> the names of the constraints :data:`COST_COMPONENTS` gives, in order.
COMPONENT_NAMES: dict[str, tuple[str, ...]] = {
    "SafetyPointCircle2-v0": WALLS,
}


def cost_components(env_id: str) -> Callable[[object], dict[str, float]]:
    """The per-constraint costs of ``env_id`` (:data:`COST_COMPONENTS`); a task without them raises, naming those
    that have them.

    Examples:
        >>> cost_components("SafetyPointCircle2-v0").__name__
        'boundary_walls'
    """
    if env_id not in COST_COMPONENTS:
        raise ValueError(
            f"{env_id} has no per-constraint costs; tasks that have them: {', '.join(COST_COMPONENTS)}"
        )
    return COST_COMPONENTS[env_id]
