"""Score expert training checkpoints to pick the four policy types (paper appendix F.2, Table I).

    python recipes/score_checkpoints.py runs/experts/hc_ppolag --env-id SafetyHalfCheetahVelocity-v1
    python recipes/score_checkpoints.py runs/experts/pc1_ppo/ckpt_000150000.pt --episodes 50

Each checkpoint (``ckpt_*.pt`` of ``recipes/train_experts.py``, or a zoo policy file) is rolled out for
``--episodes`` episodes with sampled actions, as the data is collected (:func:`spoil_torchrl.envs.rollout.rollout`,
seeded), and one markdown row is printed per checkpoint: training frames, mean ± standard error of return,
feasible return and cost over the episodes, and the share of episodes whose cost exceeds the task's limit.
``--every`` keeps every k-th checkpoint of a folder. ``safe-high`` is then the checkpoint with the best return
whose mean cost is within the limit, ``unsafe-high`` the unconstrained run's last one, and the ``-medium`` types
those near half of the ``-high`` returns (docs/experts.md).

``--components`` adds, in a task that computes its constraints' own costs (SafetyPointCircle2: ``x_wall``,
``y_wall``), a column per constraint: its mean episode cost and the share of episodes within the limit on it
(for demonstrators trained against one constraint, ``docs/several_constraints.md``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from spoil_torchrl.data.constraint_costs import episode_constraint_costs
from spoil_torchrl.data.episodes import episodes_from_arrays
from spoil_torchrl.envs.cost_components import cost_components
from spoil_torchrl.envs.rollout import rollout
from spoil_torchrl.eval import mean_stderr, transition_episode_metrics
from spoil_torchrl.tasks import get_env_task
from spoil_torchrl.zoo.policy_files import PolicyFileError, load_policy


def checkpoints(paths: list[Path], every: int) -> list[Path]:
    """The files named (folders expand to their ``*.pt`` files, sorted, every ``every``-th kept)."""
    out = []
    for path in paths:
        if path.is_dir():
            files = sorted(path.glob("*.pt"))
            if not files:
                raise FileNotFoundError(f"{path}: no .pt files")
            out += files[every - 1 :: every]
        elif path.is_file():
            out.append(path)
        else:
            raise FileNotFoundError(f"{path}: no such file or folder")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("paths", nargs="+", type=Path, help="checkpoint files or folders of them")
    parser.add_argument("--env-id", default="SafetyPointCircle1-v0", help="the task the policies act in")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--every", type=int, default=1, help="keep every k-th checkpoint of a folder")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--num-envs", type=int, default=8)
    parser.add_argument("--components", action="store_true", help="a column per constraint's own cost")
    args = parser.parse_args()
    if args.episodes < 2 or args.every < 1:
        parser.error("--episodes must be >= 2 (a standard error needs two) and --every >= 1")
    torch.set_num_threads(1)
    try:
        task = get_env_task(args.env_id)
        files = checkpoints(args.paths, args.every)
        if not files:
            raise FileNotFoundError(
                f"no checkpoint left with --every {args.every}: the folders hold fewer files"
            )
        policies = [(path, *load_policy(path, env_id=args.env_id)) for path in files]
        split = cost_components(args.env_id) if args.components else None
    except (KeyError, ValueError, FileNotFoundError, PolicyFileError) as error:
        parser.error(str(error).strip("'\""))
    print(
        f"{args.env_id}: {args.episodes} sampled-action episodes per checkpoint, seed {args.seed}, "
        f"cost limit {task.cost_limit:g}\n"
    )
    header = ["checkpoint", "frames", "return", "feasible return", "cost", "episodes over the limit"]
    start = time.perf_counter()
    for index, (path, actor, meta) in enumerate(policies):
        arrays = rollout(
            args.env_id,
            actor,
            args.episodes,
            seed=args.seed,
            num_envs=args.num_envs,
            progress=False,
            components=split,
        )
        episodes = episodes_from_arrays(arrays, source=str(path))
        metrics = transition_episode_metrics(episodes, task.cost_limit)
        keys = ("return", "feasible_return", "cost")
        cells = [f"{m:.2f} ± {s:.2f}" for m, s in (mean_stderr(metrics[k]) for k in keys)]
        over = float((metrics["cost"] > task.cost_limit).double().mean())
        cells.append(f"{100 * over:.0f} %")
        parts = episode_constraint_costs(episodes) if split is not None else {}
        for name in parts.keys():
            within = float((parts[name] <= task.cost_limit).double().mean())
            cells.append(f"{float(parts[name].mean()):.2f} ({100 * within:.0f} % within)")
        if index == 0:  # the constraints' columns are named by the first rollout
            columns = [*header, *parts.keys()]
            print("| " + " | ".join(columns) + " |\n" + "|---" * len(columns) + "|")
        frames = meta["info"].get("frames", "")
        print(f"| {path.name} | {frames} | " + " | ".join(cells) + " |", flush=True)
    print(f"\n{time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
