"""Update rate of one SpoilDICE + weighted-BC step, against the same math written in plain PyTorch.

    make bench                       # batch 512, [256, 256], obs 28 / act 2 (PointCircle1's sizes)
    python benchmarks/bench_losses.py --steps 500 --batch-size 512 --threads 2 --seeds 5

Prints updates/s, each as a ratio to the plain reference, for: the library's LossModules stepped eagerly
(``MultiLossStepper``'s step), the library's compiled step (``CompiledStepper``, ``train.compile=true``), the
compiled step with float32 products handed to oneDNN (``train.matmul_precision=medium``, the default preset's;
float32 kernels on this project's CPUs), both again with the gradient penalty's ReLU chain written out
(``train.penalty_form=relu_chain``, the presets' default: autograd's products on zeros skipped), the chain's step
with Inductor's Python wrapper instead of the C++ one the library compiles with on a CPU, K seeds vectorised
(``VectorizedStepper``, the recipe's ``seeds=[...]``: the compiled step's pure update vmapped over stacked
parameters, at medium; per seed and in total), a hand-written plain-PyTorch reference of the same step (same
networks, loss and gradient penalty; with MKL's products, the ratios' base, and at medium), and, when JAX is
installed (``pip install -e ".[bench]"``), the same step written in JAX and jit-compiled whole
(``jax_peer.py``), with XLA's count of its FLOPs.

Then the limits: the step's FLOPs (PyTorch's per-operator formulas) over a measured matmul rate of the step's
own layer shapes, by MKL and by oneDNN, for the reference's and the compiled step's arithmetic (a ceiling for
that formulation); and the limit of the machine, its rate on a large square product over the least arithmetic
that computes the step's gradients (the relu_chain form's count). The library and the reference are checked to
compute the same losses before timing. Timings on shared 2-core machines vary by 30-50 % between runs; the
ratios, measured in one run with interleaved repeats (medians), are the stable numbers. For a one-thread
comparison with the peer, pin the process to one core: ``taskset -c 1 make bench ARGS="--threads 1"``.

``--device cuda`` runs every step, batch and product on the GPU (the library's compiled steps then take CUDA
graphs, ``reduce-overhead``, as ``device=cuda`` does in the recipe; the JAX peer runs on the GPU when JAX has a
CUDA backend), and each timing waits for the device before it stops. ``medium`` there is TF32.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from tensordict import TensorDict

from spoil_torchrl.devices import training_device
from spoil_torchrl.errors import SettingsError
from spoil_torchrl.modules import make_actor, make_value_network
from spoil_torchrl.objectives import SpoilDICELoss, WeightedBCLoss
from spoil_torchrl.precision import matmul_precision, matmul_relative_error
from spoil_torchrl.trainers import CompiledStepper, MultiLossStepper
from spoil_torchrl.trainers.compiled import (
    detached,
    pure_losses,
    random_streams,
    step_inputs,
    step_parameters,
    update_gradients,
)
from spoil_torchrl.trainers.vectorized import VectorizedStepper

try:  # run as a script (make bench) or imported from benchmarks/ on sys.path
    from flops import count_flops, machine_peak, matmul_rate, synchronize
    from jax_peer import JaxStep, import_jax, jax_rate
    from reference_step import ReferenceStep
except ImportError:  # imported as benchmarks.bench_losses
    from benchmarks.flops import count_flops, machine_peak, matmul_rate, synchronize
    from benchmarks.jax_peer import JaxStep, import_jax, jax_rate
    from benchmarks.reference_step import ReferenceStep


def make_batch(n: int, n_init: int, obs_dim: int, act_dim: int) -> TensorDict:
    unlabeled = TensorDict(
        {
            "observation": torch.randn(n, obs_dim),
            "action": torch.rand(n, act_dim) * 2 - 1,
            "next": {"observation": torch.randn(n, obs_dim), "terminated": torch.rand(n, 1) < 0.01},
            "log_ratio_performant": torch.randn(n, 1),
            "safe_support": (torch.rand(n, 1) < 0.7).float(),
        },
        [n],
    )
    init = TensorDict({"observation": torch.randn(n_init, obs_dim)}, [n_init])
    return TensorDict({"unlabeled": unlabeled, "init": init}, [])


class LibraryStep:
    """One update with SpoilDICELoss + WeightedBCLoss and three Adam optimisers."""

    def __init__(
        self, obs_dim: int, act_dim: int, cells: tuple[int, ...], lr: float = 3e-5, device: str = "cpu"
    ) -> None:
        self.dice = SpoilDICELoss(
            make_value_network(obs_dim, hidden_cells=cells), gamma=0.99, gradient_penalty=10.0
        ).to(device)  # initialised on the CPU: the same weights on every device
        self.bc = WeightedBCLoss(
            make_actor(obs_dim, act_dim, hidden_cells=cells), role="unlabeled", weight="dice_weight"
        ).to(device)
        self.obs_dim = obs_dim
        self.optims = [
            torch.optim.Adam(self.dice.nu_network_params.values(True, True), lr=lr),
            torch.optim.Adam([self.dice.lagrange], lr=lr),
            torch.optim.Adam(self.bc.parameters(), lr=lr),
        ]
        self.stepper = MultiLossStepper({"dice": self.dice, "actor": self.bc}, self.optims)

    def losses(self, batch: TensorDict) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        out = self.dice(batch)
        actor = self.bc(batch)
        return out["loss_nu"], out["loss_lambda"], actor["loss_actor"]

    def __call__(self, batch: TensorDict) -> None:
        self.stepper.step(None, batch)


class CompiledLibraryStep:
    """The library's compiled step (``CompiledStepper``) over a fresh :class:`LibraryStep`'s losses, with the
    gradient penalty in ``penalty_form`` (``train.penalty_form``), compiled in ``mode`` (``None``: the library's
    default)."""

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        cells: tuple[int, ...],
        penalty_form: str = "autograd",
        mode: str | None = None,
        device: str = "cpu",
    ) -> None:
        step = LibraryStep(obs_dim, act_dim, cells, device=device)
        step.dice.penalty_form = penalty_form
        self.stepper = CompiledStepper({"dice": step.dice, "actor": step.bc}, step.optims, mode=mode)

    def __call__(self, batch: TensorDict) -> None:
        self.stepper.step(None, batch)


class VectorizedSeeds:
    """``k`` seeds' steps as one update: the library's :class:`VectorizedStepper` (the recipe's ``seeds=[...]``)
    over ``k`` fresh library steps: parameters stacked along a seed dimension, the compiled step's pure update
    vmapped and compiled, one fused Adam per optimiser over the stacked parameters, each seed's random stream.
    Each call is one step of every seed, each on its own batch (``k`` consecutive batches of ``batches``)."""

    def __init__(
        self, k: int, obs_dim: int, act_dim: int, cells: tuple[int, ...], batches, device: str = "cpu"
    ) -> None:
        seeds = [LibraryStep(obs_dim, act_dim, cells, device=device) for _ in range(k)]
        streams = random_streams(torch.device(device))
        self.stepper = VectorizedStepper([s.stepper for s in seeds], [streams] * k)
        self.k, self.batches, self.calls = k, batches, 0

    def __call__(self, batch: TensorDict) -> None:
        picked = [self.batches[(self.k * self.calls + i) % len(self.batches)] for i in range(self.k)]
        self.calls += 1
        self.stepper.step(None, picked)


def sampling_seconds(batch_size: int, obs_dim: int, act_dim: int, repeats: int = 200, device="cpu") -> float:
    """Seconds per ``DualDemoBuffers.sample()`` (safe, performant, unlabeled, init) on 600 episodes of 500 steps
    (the embedded dataset's size), D_S and D_P 10 episodes each, drawn on ``device``: the data side of one
    training step."""
    import numpy as np

    from spoil_torchrl.data import DualDemoBuffers, episodes_from_arrays

    n, rng = 300_000, np.random.default_rng(0)
    episodes = episodes_from_arrays(
        {
            "observations": rng.normal(size=(n, obs_dim)).astype(np.float32),
            "next_observations": rng.normal(size=(n, obs_dim)).astype(np.float32),
            "actions": rng.uniform(-1, 1, (n, act_dim)).astype(np.float32),
            "rewards": np.ones(n, np.float32),
            "costs": np.zeros(n, np.float32),
            "terminals": np.zeros(n, np.float32),
            "timeouts": (np.arange(1, n + 1) % 500 == 0).astype(np.float32),
        }
    )
    roles = {"safe": torch.arange(10), "performant": torch.arange(10, 20), "unlabeled": torch.arange(600)}
    buffers = DualDemoBuffers(episodes, roles, batch_size=batch_size, device=device)
    for _ in range(20):
        buffers.sample()
    synchronize(device)
    start = time.perf_counter()
    for _ in range(repeats):
        buffers.sample()
    synchronize(device)
    return (time.perf_counter() - start) / repeats


def step_flops(reference: ReferenceStep, batch: TensorDict) -> int:
    """FLOPs of one step (forward, backward, gradient penalty) of the plain reference (the eager math)."""
    flops = count_flops(lambda: sum(reference.losses(batch.clone())).backward())
    for optim in reference.optims:
        optim.zero_grad(set_to_none=True)
    return flops


def compiled_form_flops(compiled: CompiledLibraryStep, batch: TensorDict) -> int:
    """FLOPs of the compiled step's update (its pure function run eagerly): nu runs once fewer on the batch."""
    losses = compiled.stepper.losses
    params = detached(step_parameters(losses))
    inputs = step_inputs(losses, pure_losses(losses), batch.clone())
    return count_flops(lambda: update_gradients(losses)(params, inputs))


def rate(step, batches: list[TensorDict], steps: int) -> float:
    """Updates per second of ``steps`` calls of ``step``, waiting for the batches' device at both ends."""
    device = batches[0]["init", "observation"].device
    synchronize(device)
    start = time.perf_counter()
    for i in range(steps):
        step(batches[i % len(batches)])
    synchronize(device)
    return steps / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batch-size", type=int, default=512)
    parser.add_argument("--obs-dim", type=int, default=28)
    parser.add_argument("--act-dim", type=int, default=2)
    parser.add_argument("--cells", type=int, nargs="+", default=[256, 256])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seeds", type=int, default=5, help="K of the vectorised seeds (0: skip)")
    parser.add_argument("--device", default="cpu", help="cpu, or cuda (cuda:<index>): where the steps run")
    args = parser.parse_args()
    try:
        device = training_device(args.device)  # one this machine has
    except SettingsError as err:
        parser.error(str(err))
    # None: not installed (pip install -e ".[bench]"), or without a backend for the device: no peer row
    jax = import_jax(args.threads, device.type)
    torch.manual_seed(0)
    torch.set_num_threads(args.threads)
    batches = [make_batch(args.batch_size, args.batch_size, args.obs_dim, args.act_dim) for _ in range(8)]
    if device.type != "cpu":  # drawn on the CPU, so every device steps on the same data
        batches = [b.to(device) for b in batches]
    library = LibraryStep(args.obs_dim, args.act_dim, tuple(args.cells), device=device)
    reference = ReferenceStep(library)

    # Same math: with the gradient penalty off (it draws random points) the three losses must agree.
    torch.manual_seed(1)
    ours = library.losses(batches[0].clone())
    theirs = reference.losses(batches[0].clone())
    library.dice.gradient_penalty = 0.0
    ours_no_gp = library.losses(batches[0].clone())
    theirs_no_gp = reference.losses(batches[0].clone(), gp=0.0)
    library.dice.gradient_penalty = 10.0
    for a, b in zip(ours_no_gp, theirs_no_gp, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    assert all(torch.isfinite(x) for x in (*ours, *theirs))

    cells = tuple(args.cells)
    # name -> (step, float32 matmul precision it runs under: train.matmul_precision)
    steps = {"spoil_torchrl": (library, "highest"), "plain reference": (reference, "highest")}
    compile_seconds = {}
    for name, precision, make in (
        (
            "compiled",
            "highest",
            lambda: CompiledLibraryStep(args.obs_dim, args.act_dim, cells, device=device),
        ),
        (
            "compiled, medium",
            "medium",
            lambda: CompiledLibraryStep(args.obs_dim, args.act_dim, cells, device=device),
        ),
        (
            "compiled, relu_chain",
            "highest",
            lambda: CompiledLibraryStep(args.obs_dim, args.act_dim, cells, "relu_chain", device=device),
        ),
        (
            "compiled, relu_chain, medium",
            "medium",
            lambda: CompiledLibraryStep(args.obs_dim, args.act_dim, cells, "relu_chain", device=device),
        ),
        (  # the same kernels called from Inductor's Python wrapper instead of its C++ one (on a GPU: no graphs)
            "compiled, relu_chain, " + ("Python wrapper" if device.type == "cpu" else "no CUDA graphs"),
            "highest",
            lambda: CompiledLibraryStep(
                args.obs_dim, args.act_dim, cells, "relu_chain", mode="default", device=device
            ),
        ),
        (
            f"{args.seeds} seeds vmapped",
            "medium",
            lambda: VectorizedSeeds(args.seeds, args.obs_dim, args.act_dim, cells, batches, device=device),
        ),
    ):
        if name.startswith("0 seeds"):
            continue
        start = time.perf_counter()
        steps[name] = (make(), precision)
        with matmul_precision(precision):
            steps[name][0](batches[0])  # compiles
        compile_seconds[name] = time.perf_counter() - start
    steps["plain reference, medium"] = (reference, "medium")
    peer = None
    if jax is not None:
        start = time.perf_counter()
        peer = JaxStep(args.obs_dim, args.act_dim, cells)
        peer_batches = [peer.batch(b) for b in batches]
        jax_rate(peer, peer_batches, 1)  # compiles
        compile_seconds["JAX peer (XLA jit)"] = time.perf_counter() - start
    for step, precision in steps.values():  # warm-up
        with matmul_precision(precision):
            rate(step, batches, 20)
    rates: dict[str, list[float]] = {name: [] for name in steps}
    if peer is not None:
        jax_rate(peer, peer_batches, 20)
        rates["JAX peer (XLA jit)"] = []
    peaks: dict[str, list[float]] = {"highest": [], "medium": []}
    squares: dict[str, list[float]] = {"highest": [], "medium": []}
    for _ in range(args.repeats):  # interleaved, so all see the same machine load
        for name, (step, precision) in steps.items():  # (a vmapped call: a step of every seed)
            calls = max(1, args.steps // args.seeds) if name.endswith("vmapped") else args.steps
            with matmul_precision(precision):
                rates[name].append(rate(step, batches, calls))
        if peer is not None:
            rates["JAX peer (XLA jit)"].append(jax_rate(peer, peer_batches, args.steps))
        for precision, runs in peaks.items():
            with matmul_precision(precision):
                runs.append(matmul_rate(args.batch_size, args.cells, args.obs_dim, device=device))
                squares[precision].append(machine_peak(device=device))
    flops = step_flops(reference, batches[0])
    form_flops = compiled_form_flops(steps["compiled"][0], batches[0])
    least_flops = compiled_form_flops(steps["compiled, relu_chain"][0], batches[0])
    medians = {name: statistics.median(r) for name, r in rates.items()}
    peak = {precision: statistics.median(runs) for precision, runs in peaks.items()}
    square = {precision: statistics.median(runs) for precision, runs in squares.items()}
    medians["FLOP limit"] = peak["highest"] / flops
    medians["FLOP limit, compiled"] = peak["highest"] / form_flops
    medians["FLOP limit, compiled, medium"] = peak["medium"] / form_flops
    medians["limit: machine peak"] = square["highest"] / least_flops
    medians["limit: machine peak, medium"] = square["medium"] / least_flops
    step_gflops = {"JAX peer (XLA jit)": None if peer is None else peer.flops(peer_batches[0]) / 1e9}
    ref = medians["plain reference"]
    with matmul_precision("medium"):
        medium_error = matmul_relative_error(device=device)
    kernels = (
        ("MKL", "handed to oneDNN") if device.type == "cpu" else ("cuBLAS in IEEE float32", "TF32 allowed")
    )
    print(
        f"SpoilDICE + weighted-BC step, batch {args.batch_size}, cells {args.cells}, obs {args.obs_dim}, "
        f"act {args.act_dim}, on {device}, {args.threads} threads, median of {args.repeats} x {args.steps} "
        f"steps; float32 products by {kernels[0]} unless a row says medium (train.matmul_precision=medium: "
        f"{kernels[1]}, here with a relative error of {medium_error:.1e}, float32's order if below 1e-4)"
    )
    for name, value in medians.items():
        runs = rates.get(name)
        if name.endswith("vmapped"):  # a call is one step of every seed
            total = args.seeds * value
            print(
                f"  {name + ' (medium)':<28}: {value:8.1f} updates/s per seed, {total:.1f} in total   ratio to reference "
                f"{total / ref:6.2f} in total, {total / medians['spoil_torchrl']:.2f} x the eager library's "
                f"total for {args.seeds} seeds one after another   (runs: {[round(r, 1) for r in runs]}; "
                f"compiling {compile_seconds[name]:.0f} s)"
            )
            continue
        precision = "medium" if name.endswith("medium") else "highest"
        if name.startswith("limit"):
            detail = (
                f"({least_flops / 1e9:.2f} GFLOP per step, the least: the relu_chain form's count; at "
                f"{square[precision] / 1e9:.0f} GFLOP/s, {device}'s rate on a 2048 x 2048 product)"
            )
        elif runs:
            detail = f"(runs: {[round(r, 1) for r in runs]})"
            if step_gflops.get(name):
                detail += f" {step_gflops[name]:.2f} GFLOP per step by XLA's count"
        else:
            step_gflop = (form_flops if "compiled" in name else flops) / 1e9
            detail = (
                f"({step_gflop:.2f} GFLOP per step at {peak[precision] / 1e9:.0f} GFLOP/s, measured on the "
                "step's layer shapes)"
            )
        if name in compile_seconds:
            detail += f" compiling {compile_seconds[name]:.0f} s"
        print(f"  {name:<28}: {value:8.1f} updates/s   ratio to reference {value / ref:6.2f}   {detail}")
    peer_rate = medians.get("JAX peer (XLA jit)")
    if peer_rate:  # the target: the default compiled step against the peer, same run
        for name in ("compiled, relu_chain", "compiled"):
            form = "the default" if name.endswith("relu_chain") else "autograd's penalty"
            print(f"  {name} ({form}) against the JAX peer: {medians[name] / peer_rate:.2f}x")
    sample = sampling_seconds(args.batch_size, args.obs_dim, args.act_dim, device=device)
    print(
        f"  sampling the four roles: {1000 * sample:.2f} ms per batch = "
        f"{100 * sample * medians['spoil_torchrl']:.1f} % of a library step"
    )


if __name__ == "__main__":
    main()
