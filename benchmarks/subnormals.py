"""How many subnormal float32 numbers (below 1.2e-38, computed many times slower than normal ones on a CPU) a
training step makes, per operator: in the bench's step, or in a real run of the main recipe.

    python benchmarks/subnormals.py                                   # the bench's SpoilDICE + weighted-BC step
    python benchmarks/subnormals.py --algo spoildice --dataset point_circle1_mixed --every 1000 --until 5000

XLA flushes subnormal numbers to zero on CPUs and PyTorch does not, so they are a candidate for a difference in
speed between the JAX peer and our step. This counts them (eager steps, a ``TorchDispatchMode`` over every
operator's float32 outputs); the real run pre-trains as the recipe does and counts two main-stage steps every
``--every`` steps.
"""

from __future__ import annotations

import argparse
import collections
import tempfile
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

TINY = torch.finfo(torch.float32).tiny


class Subnormals(TorchDispatchMode):
    """Counts, per operator, the nonzero float32 outputs below ``TINY`` in magnitude, and all float32 outputs."""

    def __init__(self) -> None:
        super().__init__()
        self.found: collections.Counter = collections.Counter()
        self.values = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        for tensor in out if isinstance(out, (tuple, list)) else [out]:
            if isinstance(tensor, torch.Tensor) and tensor.dtype == torch.float32 and tensor.numel():
                self.values += tensor.numel()
                count = int(((tensor != 0) & (tensor.abs() < TINY)).sum())
                if count:
                    self.found[str(func)] += count
        return out


def _report(label: str, mode: Subnormals) -> None:
    top = ", ".join(f"{name} {count}" for name, count in mode.found.most_common(4))
    print(f"{label}: {sum(mode.found.values())} subnormal of {mode.values} float32 outputs ({top or 'none'})")


def bench_step(warm_up: int) -> None:
    from bench_losses import LibraryStep, make_batch

    torch.manual_seed(0)
    step = LibraryStep(28, 2, (256, 256))
    batches = [make_batch(512, 512, 28, 2) for _ in range(8)]
    for i in range(warm_up):
        step.stepper.step(None, batches[i % len(batches)])
    with Subnormals() as mode:
        for i in range(3):
            step.stepper.step(None, batches[i])
    _report(f"the bench's step, 3 steps after {warm_up}", mode)


def real_run(algo: str, dataset: str, every: int, until: int) -> None:
    from hydra import compose, initialize_config_dir

    from spoil_torchrl.runs.lifecycle import claim_runs, open_runs, pretrain
    from spoil_torchrl.runs.training import one_seed

    configs = Path(__file__).resolve().parents[1] / "configs"
    with initialize_config_dir(config_dir=str(configs), version_base="1.3"):
        cfg = compose(
            "spoildice_dsrl",
            overrides=[f"algo={algo}", f"dataset={dataset}", "progress=false"]
            + ["train.checkpoint=false", "train.compile=false"],
        )
    with claim_runs(cfg, Path(tempfile.mkdtemp())) as claim:
        steps = one_seed(pretrain(open_runs(claim)[0]))
        for done in range(every, until + 1, every):
            for _ in range(every):
                steps.stepper.step(None, steps.sample())
            with Subnormals() as mode:
                for _ in range(2):
                    steps.stepper.step(None, steps.sample())
            _report(f"{algo} on {dataset}, 2 steps after {done}", mode)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--algo", help="count in a real run of this algorithm (default: the bench's step)")
    parser.add_argument("--dataset", default="point_circle1_mixed")
    parser.add_argument("--every", type=int, default=1000)
    parser.add_argument("--until", type=int, default=5000)
    parser.add_argument("--warm-up", type=int, default=200, help="the bench's step: steps before counting")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.algo is None:
        bench_step(args.warm_up)
    else:
        real_run(args.algo, args.dataset, args.every, args.until)


if __name__ == "__main__":
    main()
