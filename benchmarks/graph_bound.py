"""How fast the compiled step's gradient graph alone runs: a bound for any wrapper around it, against the JAX peer.

    taskset -c 1 python benchmarks/graph_bound.py          # one thread, the bench's sizes, relu_chain

Three steps of the bench's SpoilDICE + weighted-BC update (``bench_losses.py``), timed interleaved with the JAX
peer (``jax_peer.py``, needs the ``bench`` extra):

* ``library``: the library's compiled step (``CompiledStepper``), as the recipe runs it;
* ``graph + Adam``: one compiled graph that computes the gradients and applies Adam (Inductor's code, not
  PyTorch's fused kernel) to parameters made into plain tensors once, with the outputs reduced in the graph;
* ``graph alone``: the same graph without any optimiser step (it returns the gradients): what the step would
  cost if everything around the gradients were free;
* ``JAX, no Adam``: the peer's jitted step without its Adam update (it returns the gradients), the peer's own
  graph alone, to compare ``graph alone`` with like for like.

The two prototypes are measurements, not training code: they skip the recipe's optimiser objects, schedules and
checkpoints. If ``graph alone`` is slower than ``JAX, no Adam``, the gap is inside the graph.
"""

from __future__ import annotations

import argparse
import statistics

import torch
from bench_losses import CompiledLibraryStep, LibraryStep, make_batch, rate
from jax_peer import JaxStep, import_jax, jax_rate

from spoil_torchrl.trainers.compiled import (
    compile_update,
    detached,
    pure_losses,
    step_inputs,
    step_parameters,
    update_gradients,
)

BETAS, EPS = (0.9, 0.999), 1e-8


class GraphStep:
    """The bench's update as one compiled graph over plain tensors, with Adam inside it or without any."""

    def __init__(self, form: str, adam: bool) -> None:
        step = LibraryStep(28, 2, (256, 256))
        step.dice.penalty_form = form
        self.losses = {"dice": step.dice, "actor": step.bc}
        self.earlier = pure_losses(self.losses)
        parameters = step_parameters(self.losses)
        lr = {
            id(p): group["lr"]
            for optim in step.optims
            for group in optim.param_groups
            for p in group["params"]
        }
        rates = {name: {key: lr[id(p)] for key, p in ps.items()} for name, ps in parameters.items()}
        self.params = detached(parameters)
        self.moments = [{n: {k: torch.zeros_like(p) for k, p in ps.items()} for n, ps in self.params.items()}]
        self.moments.append(
            {n: {k: torch.zeros_like(p) for k, p in ps.items()} for n, ps in self.params.items()}
        )
        self.count = torch.zeros(())
        gradients = update_gradients(self.losses)

        def update(params, first, second, count, inputs):
            grads, (_, outputs) = gradients(params, inputs)
            scalars = {
                n: {k: o.detach().float().mean() for k, o in out.items() if o.numel() == 1}
                for n, out in outputs.items()
            }
            if not adam:
                return grads, scalars
            count.add_(1.0)
            correction1, correction2 = 1 - BETAS[0] ** count, 1 - BETAS[1] ** count
            for n, ps in params.items():
                for k, p in ps.items():
                    g = grads[n][k]
                    first[n][k].lerp_(g, 1 - BETAS[0])
                    second[n][k].mul_(BETAS[1]).addcmul_(g, g, value=1 - BETAS[1])
                    denominator = (second[n][k].sqrt() / correction2.sqrt()).add_(EPS)
                    p.sub_(rates[n][k] * first[n][k] / correction1 / denominator)
            return scalars

        self.fn = compile_update(update, torch.device("cpu"))  # as the library compiles its step

    def __call__(self, batch) -> None:
        self.fn(self.params, *self.moments, self.count, step_inputs(self.losses, self.earlier, batch))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--form", default="relu_chain", help="train.penalty_form of all three")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--repeats", type=int, default=4)
    args = parser.parse_args()
    jax = import_jax(1)
    if jax is None:
        raise SystemExit('the JAX peer needs the bench extra: pip install -e ".[bench]"')
    torch.set_num_threads(1)
    torch.manual_seed(0)
    batches = [make_batch(512, 512, 28, 2) for _ in range(8)]
    steps = {
        "library": CompiledLibraryStep(28, 2, (256, 256), args.form),
        "graph + Adam": GraphStep(args.form, adam=True),
        "graph alone": GraphStep(args.form, adam=False),
    }
    for step in steps.values():
        rate(step, batches, 20)  # compiles, warms up
    peers = {
        "JAX peer": JaxStep(28, 2, (256, 256)),
        "JAX, no Adam": JaxStep(28, 2, (256, 256), optimizer=False),
    }
    peer_batches = [peers["JAX peer"].batch(b) for b in batches]
    for peer in peers.values():
        jax_rate(peer, peer_batches, 20)
    rates: dict[str, list[float]] = {name: [] for name in [*steps, *peers]}
    for _ in range(args.repeats):
        for name, step in steps.items():
            rates[name].append(rate(step, batches, args.steps))
        for name, peer in peers.items():
            rates[name].append(jax_rate(peer, peer_batches, args.steps))
    medians = {name: statistics.median(runs) for name, runs in rates.items()}
    for name, value in medians.items():
        runs = [round(r, 1) for r in rates[name]]
        print(
            f"  {name:<14}: {value:6.1f} updates/s   {value / medians['JAX peer']:.2f} x the peer   (runs: {runs})"
        )


if __name__ == "__main__":
    main()
