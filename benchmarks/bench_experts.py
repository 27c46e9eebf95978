"""An expert's training batch from one TorchRL environment against the same batch from environments stepped in
lockstep (``ppo.num_envs``).

    make bench                                     # runs this after the evaluation benchmark
    python benchmarks/bench_experts.py --env-id SafetyHalfCheetahVelocity-v1 --num-envs 8 --repeats 2

Each round trains one 10,000-frame batch (collection and the PPO update, one torch thread) with one environment
and then with ``--num-envs``; the two ways alternate ``--repeats`` times, and the medians are printed with their
ratio.
"""

from __future__ import annotations

import argparse
import functools
import statistics
import tempfile
import time

import torch

from spoil_torchrl.envs import make_env
from spoil_torchrl.experts.ppo import PPOConfig, train_ppo
from spoil_torchrl.tasks import get_env_task


def frames_per_second(env_id: str, num_envs: int, frames: int) -> float:
    task = get_env_task(env_id)
    config = PPOConfig(total_frames=frames, frames_per_batch=frames, minibatch_size=250, num_envs=num_envs)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as run_dir:
        train_ppo(
            functools.partial(make_env, env_id),
            task.observation_dim,
            task.action_dim,
            config,
            run_dir,
            progress=False,
            env_id=env_id,
        )
    return frames / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--env-id", default="SafetyHalfCheetahVelocity-v1")
    parser.add_argument("--num-envs", type=int, default=8)
    parser.add_argument("--frames", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(1)
    rates: dict[int, list[float]] = {1: [], args.num_envs: []}
    for _ in range(args.repeats):
        for n in rates:
            rates[n].append(frames_per_second(args.env_id, n, args.frames))
    one, many = statistics.median(rates[1]), statistics.median(rates[args.num_envs])
    print(
        f"{args.env_id}, one {args.frames}-frame batch with its PPO update (frames/s, median of {args.repeats}):"
    )
    print(f"  one TorchRL environment:        {one:8.0f}  ({', '.join(f'{r:.0f}' for r in rates[1])})")
    print(
        f"  {args.num_envs} environments in lockstep:   {many:8.0f}  "
        f"({', '.join(f'{r:.0f}' for r in rates[args.num_envs])})"
    )
    print(f"  ratio: {many / one:.2f}x")


if __name__ == "__main__":
    main()
