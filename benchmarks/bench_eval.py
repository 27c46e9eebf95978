"""One evaluation round of a ``seeds=[...]`` run: K policies evaluated one after another in this process, against
the same K evaluations with their rollouts shared with worker processes (:class:`RolloutPool`).

    make bench                                     # runs this after the data benchmark
    python benchmarks/bench_eval.py --seeds 5 --repeats 3 [--workers N]

Each round is what the recipe does per evaluation: K deterministic evaluations of ten episodes in
SafetyPointCircle1 (the default task), [256, 256] policies, every episode written to an MCAP file. The two
ways alternate, ``--repeats`` times each, and the medians are printed with their ratio; the workers' start
(spawn and imports, once per run) shows in the first round, timed apart. The episodes of both ways are checked to be equal.
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import tempfile
import time
from pathlib import Path

import torch

from spoil_torchrl.data.collect import ROLLOUT_MODULES
from spoil_torchrl.data.parallel import RolloutPool, available_cores
from spoil_torchrl.eval import Evaluator, RolloutWriter
from spoil_torchrl.modules import make_actor

ENV_ID = "SafetyPointCircle1-v0"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seeds", type=int, default=5, help="policies per round (K)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workers", type=int, default=None, help="default: one per core beyond this one")
    parser.add_argument("--episodes", type=int, default=10)
    args = parser.parse_args()
    torch.set_num_threads(2)  # as a seeds=[...] run with threads=2
    policies = []
    for k in range(args.seeds):
        torch.manual_seed(k)
        policies.append(make_actor(28, 2, hidden_cells=(256, 256)))
    workers = min(args.seeds, available_cores()) - 1 if args.workers is None else args.workers
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        evaluators = [
            Evaluator(
                ENV_ID,
                cost_threshold=10.0,
                return_range=(0.0, 50.0),
                episodes=args.episodes,
                seed=10_000 + k,
                writer=stack.enter_context(RolloutWriter(Path(tmp) / f"seed{k}.mcap", cost_threshold=10.0)),
            )
            for k in range(args.seeds)
        ]
        pool = stack.enter_context(RolloutPool(workers=workers, warm_up=ROLLOUT_MODULES))

        def shared_round() -> list[dict]:
            rollouts = pool.map([e.rollout_job(p) for e, p in zip(evaluators, policies, strict=True)])
            return [e.report(next(rollouts), step=0) for e in evaluators]

        start = time.perf_counter()
        shared_round()  # the workers start: spawn, imports
        first = time.perf_counter() - start
        times: dict[str, list[float]] = {"one after another": [], "rollouts shared": []}
        episodes = {}
        for _ in range(args.repeats):
            start = time.perf_counter()
            alone = [e(p, step=0) for e, p in zip(evaluators, policies, strict=True)]
            times["one after another"].append(time.perf_counter() - start)
            start = time.perf_counter()
            shared = shared_round()
            times["rollouts shared"].append(time.perf_counter() - start)
            episodes = {"alone": [r["episodes"] for r in alone], "shared": [r["episodes"] for r in shared]}
    if episodes["alone"] != episodes["shared"]:
        raise SystemExit("evaluation bench: the two ways gave different episodes")
    base = statistics.median(times["one after another"])
    print(
        f"evaluation round of {args.seeds} policies x {args.episodes} episodes ({ENV_ID}, [256, 256]), "
        f"{workers} worker process(es), median of {args.repeats}:"
    )
    for name, values in times.items():
        median = statistics.median(values)
        print(f"  {name:<18} {median:6.2f} s  ({base / median:.2f}x)")
    print(f"  the first shared round, workers starting: {first:.2f} s; episodes equal both ways")


if __name__ == "__main__":
    main()
